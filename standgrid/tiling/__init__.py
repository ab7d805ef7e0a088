"""Tiling: missions' payloads and an epoch's kept points into a catalog's cells and tiles.

- :mod:`.setup`: the output folder checked, a new catalog created, the tiling settings;
- :mod:`.epoch`: ``tile_epoch``, (re)tiling one epoch inside a catalog transaction;
- :mod:`.cells`: an epoch's points through the partition engine into cells, here or on a
  cluster; :mod:`.cell_task`: one cell's tile written (a pure task for an executor);
- :mod:`.increment`: re-tiling in place (only the tiles whose points change);
- :mod:`.retile`: the points an epoch keeps from its existing tiles;
- :mod:`.placement_policy`: a mission keeps its placement under a tolerance;
- :mod:`.mission_rows`: what the index records about an ingested mission;
- :mod:`.vpcs`: one virtual point cloud per epoch;
- :mod:`.elevation`: payloads' derived maps placed (elevation maps into a mosaic per epoch).

Stage order: after ``catalog`` and ``export`` (file writers), before ``enrich``. The entry
point is :func:`standgrid.pipeline.tile.tile_missions`. Nothing heavy is imported here.
"""
