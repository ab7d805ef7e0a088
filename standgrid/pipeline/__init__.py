"""Thin orchestration of the stages: tile missions into a catalog, enrich it, compare epochs."""
