"""One ``stand_metrics`` row per stand: the coverage rule, then the area- and tree-based sets.

A stand (a 20 m cell, or a 1 ha stand aggregating its cells) is measured over its
**observed** ground (:mod:`standgrid.enrichment.coverage`): heights of the points standing on
it, trees whose stem stands on it, per-hectare values divided by its area. A stand whose
observed fraction or point density is below :class:`CoverageRule` gets null metrics with
``null_reason`` starting ``insufficient_coverage``, never a number from a sliver of data.
Definitions: docs/METRICS.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from standgrid.enrichment.metrics import fmt_break
from standgrid.errors import EnrichError

INSUFFICIENT_COVERAGE = "insufficient_coverage"
NO_TERRAIN = "no ground points in or near the stand: no terrain model"
#: Columns of a stand row that describe the sample, not the forest: kept when the metrics
#: are null (they say why), never "changed" between epochs.
SAMPLE_COLUMNS = (
    "level",
    "cell_size",
    "area_m2",
    "observed_m2",
    "observed_fraction",
    "n_points",
    "n_outside_observed",
    "n_no_height",
    "density_pts_m2",
)
#: Counts of the tree sample: null with the metrics, never "changed" either.
TREE_COUNT_COLUMNS = (
    "n_trees",
    "n_dbh_measured",
    "n_dbh_imputed",
    "dbh_measured_share",
    "n_trees_by_stem",
    "stem_detected_share",
    "tree_detection_note",
)
#: Below this share of trees found from their stem, the trees come from canopy tops
#: (airborne data, or stems a ground robot could not see): the stand table says what that
#: misses.
MIN_STEM_SHARE = 0.5
#: Share of returns above the height break over a stand that shows a canopy stands there.
MIN_CANOPY_PERCENT = 10.0
TOPS_ONLY_NOTE = (
    "trees found from canopy tops ({by_stem} of {n} from their stem): trees under the "
    "canopy (understorey, suppressed) are not seen from above, so stems_ha and "
    "basal_area_m2_ha are lower bounds"
)
NO_TOP_IN_STAND = (
    "no tree top in the stand, yet {cover:.0f} % of its returns are canopy above {brk:g} m: "
    "the crowns over it belong to trees whose tops stand in neighbouring stands (trees "
    "found from canopy tops), so its stems and basal area are unknown, not 0"
)


@dataclass(frozen=True)
class CoverageRule:
    """The least a stand must have observed for its metrics to be reported."""

    min_observed_fraction: float = 0.25
    min_density_pts_m2: float = 2.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_observed_fraction <= 1.0 or self.min_density_pts_m2 < 0:
            raise EnrichError(
                f"coverage rule needs 0 <= min observed fraction <= 1 (got "
                f"{self.min_observed_fraction}) and min density >= 0 "
                f"(got {self.min_density_pts_m2})"
            )

    def shortfall(self, observed_fraction: float, density: float) -> str | None:
        """Why a stand fails the rule (``insufficient_coverage: ...``), or None."""
        problems = []
        if not observed_fraction >= self.min_observed_fraction:
            problems.append(
                f"{100 * observed_fraction:.0f} % of the stand observed "
                f"(minimum {100 * self.min_observed_fraction:.0f} %)"
            )
        if not density >= self.min_density_pts_m2:
            shown = 0.0 if not math.isfinite(density) else density
            problems.append(
                f"{shown:.2g} points/m2 on observed ground (minimum {self.min_density_pts_m2:g})"
            )
        return f"{INSUFFICIENT_COVERAGE}: " + ", ".join(problems) if problems else None


@dataclass
class StandSample:
    """What one stand's metrics are computed from."""

    stand_id: str
    level: int
    cell_size: float
    area_m2: float
    observed_m2: float
    #: every return of the stand, observed ground or not
    n_points: int
    #: heights above ground of the returns on observed ground (NaN: no terrain height);
    #: may be released once :attr:`area` is measured (:meth:`release_heights`)
    heights: NDArray[np.floating]
    #: trees whose stem (or top, without a stem fit) stands on observed ground
    trees: pd.DataFrame
    no_ground: bool = False
    #: the area-based metrics of ``heights`` (:func:`measure_heights`), once measured
    area: dict[str, Any] | None = None
    #: the cells a coarser stand aggregates (their trees are its trees)
    members: tuple[str, ...] = ()
    #: returns on observed ground (``len(heights)`` until the heights are released)
    n_on_observed: int = -1

    def __post_init__(self) -> None:
        if self.n_on_observed < 0:
            self.n_on_observed = len(self.heights)

    @property
    def observed_fraction(self) -> float:
        return self.observed_m2 / self.area_m2 if self.area_m2 > 0 else math.nan

    def density(self) -> float:
        """Returns per square metre of observed ground."""
        return self.n_on_observed / self.observed_m2 if self.observed_m2 > 0 else math.nan

    def measured(self, rule: CoverageRule) -> bool:
        """Whether the stand gets metrics: it has terrain and passes the coverage rule."""
        return not self.no_ground and rule.shortfall(self.observed_fraction, self.density()) is None

    def release_heights(self) -> None:
        """Drop the heights (their metrics are measured), keeping their count."""
        if self.area is None:
            raise EnrichError(f"stand {self.stand_id}: heights released before measured")
        self.heights = np.zeros(0, dtype=np.float32)


def stand_row(
    sample: StandSample,
    rule: CoverageRule,
    *,
    height_break: float = 2.0,
    tops_only: bool = False,
) -> dict[str, Any]:
    """One ``stand_metrics`` row (columns: docs/METRICS.md)."""
    return stand_rows_of([sample], rule, height_break=height_break, tops_only=tops_only)[0]


def stand_rows_of(
    samples: list[StandSample],
    rule: CoverageRule,
    *,
    height_break: float = 2.0,
    tops_only: bool = False,
) -> list[dict[str, Any]]:
    """The ``stand_metrics`` row of each sample (area metrics measured where not yet, tree
    metrics for many at once). ``tops_only``: the epoch's trees come mostly from canopy tops
    (:func:`tops_only`), so a stand under canopy without a tree top of its own has unknown
    stems, not none."""
    measure_heights(samples, height_break=height_break)
    rows: list[dict[str, Any]] = []
    for start in range(0, len(samples), TREE_BATCH):
        batch = samples[start : start + TREE_BATCH]
        rows += _batch_rows(batch, rule, height_break, tops_only)
    return rows


def tops_only(trees: pd.DataFrame) -> bool:
    """Whether fewer than :data:`MIN_STEM_SHARE` of ``trees`` were found from their stem
    (airborne data: the stand table says what canopy tops miss)."""
    if not len(trees) or "detected_by" not in trees.columns:
        return False
    return float(trees["detected_by"].isin(("stem", "both")).mean()) < MIN_STEM_SHARE


#: Heights measured at once (~100 MB of working arrays).
BATCH_HEIGHTS = 2_000_000
#: Stands whose tree metrics are computed at once.
TREE_BATCH = 10_000


def measure_heights(
    samples: list[StandSample], *, height_break: float = 2.0, sort_heights: bool = False
) -> None:
    """Fill :attr:`StandSample.area` of the samples not measured yet, many at once, in
    batches of at most :data:`BATCH_HEIGHTS` heights (memory stays bounded). With
    ``sort_heights``, their heights are left sorted (the finite ones, then the others), as a
    coarser stand merges them: the measurement sorts them anyway."""
    batch: list[StandSample] = []
    size = 0
    for sample in (s for s in samples if s.area is None):
        if batch and size + len(sample.heights) > BATCH_HEIGHTS:
            _measure_batch(batch, height_break, sort_heights)
            batch, size = [], 0
        batch.append(sample)
        size += len(sample.heights)
    if batch:
        _measure_batch(batch, height_break, sort_heights)


def _measure_batch(samples: list[StandSample], height_break: float, sort_heights: bool) -> None:
    from standgrid.enrichment.metrics import area_metrics_sorted

    keys = np.arange(len(samples), dtype=np.int64)
    # float32 heights (as enrichment holds them) stay float32: the metrics sort them as such
    heights = np.concatenate([np.asarray(s.heights) for s in samples])
    table, ordered = area_metrics_sorted(
        np.repeat(keys, [len(s.heights) for s in samples]),
        heights,
        cells=keys,
        height_break=height_break,
    )
    rows = table.to_dict("records")
    if sort_heights:
        n_finite = (table["n_points"] - table["n_no_height"]).to_numpy()
        parts = np.split(ordered, np.cumsum(n_finite)[:-1])
        for sample, part in zip(samples, parts, strict=True):
            given = np.asarray(sample.heights)
            sample.heights = np.concatenate([part, given[~np.isfinite(given)]])  # a copy
    for sample, row in zip(samples, rows, strict=True):
        sample.area = row


def _batch_rows(
    samples: list[StandSample], rule: CoverageRule, height_break: float, tops: bool
) -> list[dict[str, Any]]:
    from standgrid.enrichment.metrics import tree_metrics

    keys = np.arange(len(samples), dtype=np.int64)
    with_trees = [(k, s.trees) for k, s in enumerate(samples) if len(s.trees)]
    trees = (
        pd.concat([t.assign(_key=k) for k, t in with_trees], ignore_index=True)
        if with_trees
        else samples[0].trees.assign(_key=np.zeros(0, dtype=np.int64))
    )
    source = trees["dbh_source"] if "dbh_source" in trees.columns else None
    tree_table = tree_metrics(
        trees["_key"].to_numpy(dtype=np.int64),
        trees["height_m"].to_numpy(dtype=np.float64),
        trees["dbh_m"].to_numpy(dtype=np.float64),
        cell_area_m2=np.array([max(s.observed_m2, 1e-9) for s in samples]),
        cells=keys,
        dbh_measured=None if source is None else (source == "measured").to_numpy(dtype=bool),
    )
    by_stem = np.zeros(len(samples), dtype=np.int64)
    if "detected_by" in trees.columns and len(trees):
        stem_found = trees["detected_by"].isin(("stem", "both")).to_numpy(dtype=bool)
        by_stem = np.bincount(trees["_key"].to_numpy(np.int64)[stem_found], minlength=len(samples))
    rows = []
    for k, (sample, tree_row) in enumerate(
        zip(samples, tree_table.to_dict("records"), strict=True)
    ):
        _detection(tree_row, int(by_stem[k]), sample.area or {}, height_break, tops)
        rows.append(_row(sample, sample.area or {}, tree_row, rule))
    return rows


def _detection(
    tree_row: dict[str, Any],
    by_stem: int,
    area_row: dict[str, Any],
    height_break: float,
    tops: bool,
) -> None:
    """Say in ``tree_row`` how its trees were found and what that misses (in place): trees
    found from their stem, their share, a note where most came from canopy tops, and null
    counts for a stand under canopy whose trees' tops all stand elsewhere."""
    n = int(tree_row["n_trees"])
    tree_row["n_trees_by_stem"] = by_stem
    tree_row["stem_detected_share"] = by_stem / n if n else math.nan
    note = None
    if n and by_stem < MIN_STEM_SHARE * n:
        note = TOPS_ONLY_NOTE.format(by_stem=by_stem, n=n)
    cover = float(area_row.get(f"pzabove{fmt_break(height_break)}", math.nan))
    if not n and tops and cover >= MIN_CANOPY_PERCENT:
        for name in ("stems_ha", "basal_area_m2_ha", "qmd_cm"):
            tree_row[name] = math.nan
        tree_row["null_reason"] = NO_TOP_IN_STAND.format(cover=cover, brk=height_break)
    tree_row["tree_detection_note"] = note


def _row(
    sample: StandSample, area_row: dict[str, Any], tree_row: dict[str, Any], rule: CoverageRule
) -> dict[str, Any]:
    observed = sample.observed_m2
    n_on_observed = sample.n_on_observed
    density = sample.density()
    row: dict[str, Any] = {
        "cell_id": sample.stand_id,
        "level": sample.level,
        "cell_size": sample.cell_size,
        "area_m2": sample.area_m2,
        "observed_m2": observed,
        "observed_fraction": sample.observed_fraction,
        "n_points": sample.n_points,
        "n_outside_observed": sample.n_points - n_on_observed,
    }
    row.update({k: v for k, v in area_row.items() if k not in ("null_reason", "n_points")})
    row["density_pts_m2"] = density
    row.update({k: v for k, v in tree_row.items() if k != "null_reason"})

    shortfall = rule.shortfall(sample.observed_fraction, density)
    if sample.no_ground:
        reasons = [NO_TERRAIN]
    elif shortfall:
        reasons = [shortfall]
    else:
        reasons = [
            str(r) for r in (area_row.get("null_reason"), tree_row.get("null_reason")) if _text(r)
        ]
    if sample.no_ground or shortfall:  # unknown, not zero
        for name in (*area_row, *tree_row):
            if name in row and name not in SAMPLE_COLUMNS and name != "null_reason":
                row[name] = None if name == "dominant_by" else math.nan
    row["null_reason"] = "; ".join(dict.fromkeys(str(r) for r in reasons)) or None
    return row


def aggregate(
    stand_id: str, cell_size: float, area_m2: float, members: list[StandSample]
) -> StandSample:
    """A coarser stand from its measured member cells (the others contribute no area)."""
    released = [m.stand_id for m in members if len(m.heights) != m.n_on_observed]
    if released:
        raise EnrichError(f"stand {stand_id}: cells {released[:3]} no longer hold their heights")
    frames = [m.trees for m in members if len(m.trees)]
    return StandSample(
        stand_id=stand_id,
        level=1,
        cell_size=cell_size,
        area_m2=area_m2,
        observed_m2=float(sum(m.observed_m2 for m in members)),
        n_points=int(sum(m.n_points for m in members)),
        heights=(
            np.concatenate([m.heights for m in members]) if members else np.zeros(0, np.float32)
        ),
        trees=(
            pd.concat(frames, ignore_index=True)
            if frames
            else pd.DataFrame({"height_m": [], "dbh_m": []})
        ),
        no_ground=False,
        members=tuple(m.stand_id for m in members),
    )


class StandAggregator:
    """Coarser stands measured as soon as all their cells are in, so a cell's heights are
    held only until its stand is complete (cells arrive chunk by chunk)."""

    def __init__(
        self,
        stand_of: dict[str, str | None],
        stand_size: float | None,
        rule: CoverageRule,
        *,
        height_break: float,
    ) -> None:
        self.stand_size = stand_size
        self.rule = rule
        self.height_break = height_break
        self.stand_of = stand_of if stand_size is not None else {}
        self._waiting: dict[str, int] = {}
        for stand in self.stand_of.values():
            if stand is not None:
                self._waiting[stand] = self._waiting.get(stand, 0) + 1
        self._members: dict[str, list[StandSample]] = {s: [] for s in self._waiting}
        self.stands: dict[str, StandSample] = {}

    def holds(self, sample: StandSample) -> bool:
        """Whether a cell's heights are still needed (it counts toward a coarser stand)."""
        return self.stand_of.get(sample.stand_id) is not None and sample.measured(self.rule)

    def add(self, cells: list[StandSample]) -> None:
        """Take measured cells; measure the stands they complete; release the cells' heights."""
        measure_heights(cells, height_break=self.height_break)
        complete: list[str] = []
        for cell in cells:
            stand = self.stand_of.get(cell.stand_id)
            if stand is not None and self.holds(cell):
                self._members[stand].append(cell)
            elif len(cell.heights):
                cell.release_heights()
            if stand is not None:
                self._waiting[stand] -= 1
                if self._waiting[stand] == 0:
                    complete.append(stand)
        size = self.stand_size or 0.0  # complete stands exist only with a stand size
        done = []
        for stand_id in complete:
            # in id order, not arrival order: a stand's sums are the same whatever the chunks
            members = sorted(self._members.pop(stand_id), key=lambda m: m.stand_id)
            done.append(aggregate(stand_id, size, size * size, members))
            for member in members:
                member.release_heights()  # the stand holds a copy
        measure_heights(done, height_break=self.height_break)
        for sample in done:
            sample.release_heights()
            self.stands[sample.stand_id] = sample

    def result(self) -> list[StandSample]:
        """Every coarser stand, sorted by id (all cells must have been added)."""
        missing = sorted(s for s, n in self._waiting.items() if n > 0)
        if missing:
            raise EnrichError(f"stands {missing[:5]} still miss cells")
        return [self.stands[s] for s in sorted(self.stands)]


def stem_xy(trees: pd.DataFrame) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Where each tree's stem stands: the fitted stem centre, or its top without a fit."""
    x = trees["x"].to_numpy(np.float64)
    y = trees["y"].to_numpy(np.float64)
    if "stem_x" not in trees.columns:
        return x, y
    sx = trees["stem_x"].to_numpy(np.float64)
    sy = trees["stem_y"].to_numpy(np.float64)
    fitted = np.isfinite(sx) & np.isfinite(sy)
    return np.where(fitted, sx, x), np.where(fitted, sy, y)


def counted_trees(trees: pd.DataFrame, metrics: pd.DataFrame) -> pd.Series:
    """The trees an epoch's ``stand_metrics`` rows count: stem on observed ground, top in a
    20 m cell whose metrics are reported (so also in its measured 1 ha stand)."""
    cells = metrics[metrics["level"] == 0]
    measured = set(cells.loc[cells["stems_ha"].notna(), "cell_id"])
    return trees["observed"].astype(bool) & trees["cell_id"].isin(measured)


def _text(value: Any) -> bool:
    """True for a real reason text (not None, NaN or pandas NA)."""
    return isinstance(value, str) and value != ""


def stand_rows(
    cells: list[StandSample],
    stands: list[StandSample],
    trees: pd.DataFrame,
    rule: CoverageRule,
    *,
    height_break: float,
) -> list[dict[str, Any]]:
    """Every cell's row, then every coarser stand's (from :class:`StandAggregator`): a stand
    aggregates the observed ground, points and trees of its cells that pass the coverage
    rule; its area is the whole stand's."""
    on_ground = trees[trees["observed"]] if len(trees) else trees
    by_cell = dict(tuple(on_ground.groupby("cell_id"))) if len(on_ground) else {}
    empty = trees.iloc[0:0]
    for cell in cells:
        cell.trees = by_cell.get(cell.stand_id, empty)
    for stand in stands:
        frames = [by_cell[m] for m in stand.members if m in by_cell]
        stand.trees = pd.concat(frames, ignore_index=True) if frames else empty
    tops = tops_only(trees)
    return stand_rows_of(cells, rule, height_break=height_break, tops_only=tops) + stand_rows_of(
        stands, rule, height_break=height_break, tops_only=tops
    )
