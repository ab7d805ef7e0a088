"""Height-diameter model: a DBH for the trees whose stem could not be fitted.

Näslund's height curve ``h = 1.3 + d² / (a + b d)²`` (Näslund 1937; d in cm, h in m) is
the standard height-diameter form of Nordic forest inventories. Solved for the diameter,

    d = a s / (1 - b s),   s = sqrt(h - 1.3),

it predicts the DBH of a tree from its height. standgrid fits ``a`` and ``b`` to an
epoch's measured trees (stem fits) by least squares on ``log d`` (a multiplicative error:
the scatter of DBH grows with DBH), then imputes ``d = f(h) · exp(σ²/2)`` (the mean, not the
median, of the log-normal error, so sums of diameters are unbiased) with a standard error
``d · sqrt(exp(σ²) - 1)``. Heights within 5 % of the curve's asymptote (``b s -> 1``) are
taken at that limit and flagged. With fewer than ``min_trees`` measured trees in the
epoch the catalog's measured trees of all epochs are pooled; with fewer than that in the
whole catalog, nothing is imputed (null DBH with a reason), never a guess.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    import pandas as pd

    from standgrid.catalog import Catalog

BREAST_HEIGHT_M = 1.3
#: Measured trees needed to fit the model.
MIN_TREES = 15
#: Imputation stops at this share of the asymptote (b s < MAX_BS).
MAX_BS = 0.95


@dataclass(frozen=True)
class HeightDiameterModel:
    """A fitted Näslund curve: parameters, log-residual SD, the data it was fitted on."""

    a: float
    b: float
    sigma_log: float
    n_trees: int
    height_range_m: tuple[float, float]
    source: str

    def predict_dbh_m(self, height_m: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Mean DBH (m) for each height, and whether the asymptote limit was used."""
        h = np.asarray(height_m, dtype=np.float64)
        s = np.sqrt(np.clip(h - BREAST_HEIGHT_M, 0.0, None))
        limited = self.b * s > MAX_BS
        if self.b > 0:
            s = np.minimum(s, MAX_BS / self.b)
        d_cm = self.a * s / (1.0 - self.b * s)
        return d_cm * math.exp(self.sigma_log**2 / 2.0) / 100.0, limited

    def dbh_se_m(self, dbh_m: ArrayLike) -> NDArray[np.float64]:
        """Standard error of an imputed DBH (m): the model's log-normal scatter."""
        return np.asarray(dbh_m, dtype=np.float64) * math.sqrt(math.expm1(self.sigma_log**2))

    def to_dict(self) -> dict[str, Any]:
        return {
            "form": "naslund",
            "a": self.a,
            "b": self.b,
            "sigma_log": self.sigma_log,
            "n_trees": self.n_trees,
            "height_range_m": list(self.height_range_m),
            "source": self.source,
        }


def fit_height_diameter(
    height_m: ArrayLike, dbh_m: ArrayLike, *, source: str = "epoch"
) -> HeightDiameterModel | None:
    """Fit Näslund's curve to measured trees; None when fewer than :data:`MIN_TREES` usable."""
    from scipy.optimize import least_squares

    h = np.asarray(height_m, dtype=np.float64)
    d_cm = np.asarray(dbh_m, dtype=np.float64) * 100.0
    ok = np.isfinite(h) & np.isfinite(d_cm) & (h > BREAST_HEIGHT_M + 0.1) & (d_cm > 0)
    h, d_cm = h[ok], d_cm[ok]
    if len(h) < MIN_TREES:
        return None
    s = np.sqrt(h - BREAST_HEIGHT_M)
    log_d = np.log(d_cm)
    # start from the linearised form d / s = a + b d (ordinary least squares)
    design = np.column_stack([np.ones_like(d_cm), d_cm])
    (a0, b0), *_ = np.linalg.lstsq(design, d_cm / s, rcond=None)
    a0 = max(float(a0), 1e-3)
    b_max = MAX_BS / float(s.max())  # every measured tree below the asymptote
    b0 = min(max(float(b0), 0.0), 0.9 * b_max)

    def residuals(p: NDArray[np.float64]) -> NDArray[np.float64]:
        a, b = p
        return log_d - np.log(a * s / (1.0 - b * s))

    fit = least_squares(
        residuals, x0=[a0, b0], bounds=([1e-6, 0.0], [np.inf, b_max]), loss="soft_l1", f_scale=0.2
    )
    a, b = (float(v) for v in fit.x)
    r = residuals(fit.x)
    # robust scale (MAD), so a few mis-fitted stems do not inflate the stated uncertainty
    sigma = float(1.4826 * np.median(np.abs(r - np.median(r))))
    return HeightDiameterModel(a, b, sigma, len(h), (float(h.min()), float(h.max())), source)


def impute_dbh(trees: Any, model: HeightDiameterModel | None) -> Any:
    """Fill ``dbh_m`` of the trees without a measured DBH; returns a new table.

    Adds ``dbh_source`` (``measured`` | ``imputed`` | ``none``) and ``dbh_se_m``; measured
    trees keep their fit and its standard error (the table's ``dbh_se_m``, else ``2 rmse /
    sqrt(n)`` of the circle fit). Without a
    model, unmeasured trees keep a null DBH and ``dbh_reason`` says why.
    """
    import pandas as pd

    table = trees.copy()
    dbh = table["dbh_m"].to_numpy(dtype=np.float64, copy=True)
    measured = np.isfinite(dbh)
    source = np.where(measured, "measured", "none").astype(object)
    se = np.full(len(table), np.nan)
    if "dbh_se_m" in table.columns:  # a stem's own (its circles' spread and residuals)
        se[measured] = table["dbh_se_m"].to_numpy(dtype=np.float64)[measured]
    elif "dbh_rmse_m" in table.columns and "dbh_n_points" in table.columns:
        rmse = table["dbh_rmse_m"].to_numpy(dtype=np.float64)
        n = table["dbh_n_points"].to_numpy(dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            se[measured] = 2.0 * rmse[measured] / np.sqrt(n[measured])
    reason = table["dbh_reason"].astype("object").to_numpy(copy=True)
    missing = ~measured
    if model is not None and missing.any():
        value, limited = model.predict_dbh_m(table["height_m"].to_numpy(dtype=np.float64)[missing])
        dbh[missing] = value
        se[missing] = model.dbh_se_m(value)
        source[missing] = "imputed"
        note = np.where(limited, "; height beyond the curve's range: DBH at its limit", "")
        reason[missing] = [
            f"imputed from height ({model.source} height-diameter model): {r}{extra}"
            for r, extra in zip(reason[missing], note, strict=True)
        ]
    elif missing.any():
        reason[missing] = [
            f"{r}; no height-diameter model (fewer than {MIN_TREES} measured stems "
            "in the catalog), so no DBH"
            for r in reason[missing]
        ]
    table["dbh_m"] = dbh
    table["dbh_source"] = pd.array(source, dtype="string")
    table["dbh_se_m"] = se
    table["dbh_reason"] = pd.array(reason, dtype="string")
    return table


def height_diameter_models(
    catalog: Catalog, trees: dict[str, pd.DataFrame]
) -> dict[str, HeightDiameterModel | None]:
    """Per epoch: its own height-diameter model, or one pooled over the catalog's epochs
    (the measured trees of ``trees`` and of the tree lists of epochs enriched before)."""
    import pandas as pd

    from standgrid.catalog import paths
    from standgrid.catalog.invalidate import POOLED_MODEL

    measured = {e: t[np.isfinite(t["dbh_m"].to_numpy(np.float64))] for e, t in trees.items()}
    for epoch in catalog.epochs:  # measured trees of epochs enriched before
        path = catalog.path(paths.tree_list(epoch, "parquet"))
        if epoch not in measured and path.exists():
            old = pd.read_parquet(path)
            if "dbh_source" in old.columns:
                measured[epoch] = old[old["dbh_source"] == "measured"]
    frames = [m[["height_m", "dbh_m"]] for m in measured.values() if len(m)]
    pooled_trees = pd.concat(frames, ignore_index=True) if frames else None
    pooled = None
    if pooled_trees is not None:
        pooled = fit_height_diameter(
            pooled_trees["height_m"], pooled_trees["dbh_m"], source=POOLED_MODEL
        )
    models: dict[str, HeightDiameterModel | None] = {}
    for epoch in trees:
        own = measured[epoch]
        model = fit_height_diameter(own["height_m"], own["dbh_m"], source=f"epoch {epoch}")
        models[epoch] = model or pooled
    return models


def tree_summary(trees: pd.DataFrame, model: HeightDiameterModel | None) -> dict[str, Any]:
    source = trees["dbh_source"] if len(trees) else None
    return {
        "trees": len(trees),
        "trees_on_observed_ground": int(trees["observed"].sum()) if len(trees) else 0,
        "trees_dbh_measured": int((source == "measured").sum()) if source is not None else 0,
        "trees_dbh_imputed": int((source == "imputed").sum()) if source is not None else 0,
        "trees_dbh_none": int((source == "none").sum()) if source is not None else 0,
        "height_diameter_model": model.to_dict() if model is not None else None,
    }
