"""Features that persist between visits, found in points of any stage: stems as chains of
circles (:mod:`.stems`) and the circle fits they are made of (:mod:`.circles`). Used by
alignment (before tiling) and by enrichment (trees)."""
