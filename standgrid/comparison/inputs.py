"""What a comparison reads of a catalog: its enriched epochs, their dates, stand metrics and
tree lists (a missing or stale input is an error that says which command to run)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from standgrid.catalog import paths
from standgrid.errors import EnrichError, EpochNotFoundError

if TYPE_CHECKING:
    import pandas as pd

    from standgrid.catalog import Catalog


def read_table(catalog: Catalog, rel: str) -> pd.DataFrame:
    import pandas as pd

    path = catalog.path(rel)
    if not path.exists():
        raise EnrichError(
            f"{rel} is missing: run `standgrid enrich {catalog.root}` first", path=path
        )
    return pd.read_parquet(path)


def default_epoch(catalog: Catalog, *, first: bool, both_from_it: bool = True) -> str:
    """The first (``first``) or last epoch of ``catalog`` by date. When both epochs come from
    it (no other catalog), it needs two; else one is enough."""
    records = catalog.epoch_records
    epochs = sorted(records, key=lambda e: (records[e].date or "", e))
    if len(epochs) < (2 if first and both_from_it else 1):
        needs = (
            "two epochs (or option other_catalog: a second catalog)" if both_from_it else "an epoch"
        )
        raise EpochNotFoundError(
            f"comparing needs {needs}; the catalog has {epochs or 'none'}",
            path=catalog.root,
            option="other_catalog" if both_from_it else None,
        )
    return epochs[0] if first else epochs[-1]


def enriched_epoch(catalog: Catalog, epoch: str) -> str:
    """The epoch's date; raises unless the epoch exists and is enriched."""
    entry = catalog.epoch(epoch)  # EpochNotFoundError naming the epochs
    if not entry.enriched:
        raise EnrichError(
            f"epoch {epoch!r} is not enriched (run `standgrid enrich {catalog.root}` first)",
            path=catalog.root,
        )
    if not entry.date:
        raise EnrichError(f"epoch {epoch!r} has no date to annualise with", path=catalog.root)
    return entry.date


def epoch_metrics(catalog: Catalog, epoch: str) -> pd.DataFrame:

    table = read_table(catalog, paths.stand_metrics("parquet"))
    return table[table["epoch"].astype(str) == epoch].drop(columns=["epoch"]).reset_index(drop=True)
