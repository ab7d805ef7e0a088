"""Enrichment: terrain, trees and stand metrics."""
