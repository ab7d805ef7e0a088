"""Detected trees against the simulator's truth: pairing and the figures issue 19 asks for.

A detected tree is paired (one to one, least total distance) with a true tree standing at
the scan: a tree found from its stem when its stem position at 1.3 m is within 0.5 m of
the true stem's, a tree found from its top only when its top is within 1.5 m of the true
crown's centre and its height within 25 % of the true tree's (a canopy top is the top of a
tree that reaches it, not of a small tree under it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

from standgrid.simulate.canopy import crown_centres
from standgrid.simulate.forest import Trees

STEM_MATCH_M = 0.5
TOP_MATCH_M = 1.5
TOP_HEIGHT_SHARE = 0.25
KINDS = ("overstorey", "understorey", "snag")


def truth_table(trees: Trees) -> pd.DataFrame:
    """The standing true trees: stem at breast height, crown centre, DBH, height, kind."""
    standing = trees.standing
    centres = crown_centres(trees)
    return pd.DataFrame(
        {
            "x": trees.x_bh,
            "y": trees.y_bh,
            "cx": centres[:, 0],
            "cy": centres[:, 1],
            "dbh": trees.dbh,
            "height": trees.height,
            "kind": trees.kind,
        }
    )[standing].reset_index(drop=True)


def pair(found: pd.DataFrame, truth: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``found`` and ``truth`` paired (module doc)."""
    if not len(found) or not len(truth):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    by_top = (found["detected_by"] == "top").to_numpy()
    at_stem = np.hypot(
        found["x"].to_numpy()[:, None] - truth["x"].to_numpy()[None],
        found["y"].to_numpy()[:, None] - truth["y"].to_numpy()[None],
    )
    at_top = np.hypot(
        found["top_x"].to_numpy()[:, None] - truth["cx"].to_numpy()[None],
        found["top_y"].to_numpy()[:, None] - truth["cy"].to_numpy()[None],
    )
    distance = np.where(by_top[:, None], at_top, at_stem)
    limit = np.where(by_top, TOP_MATCH_M, STEM_MATCH_M)[:, None]
    ratio = found["height_m"].to_numpy()[:, None] / truth["height"].to_numpy()[None]
    plausible = ~by_top[:, None] | (np.abs(ratio - 1.0) <= TOP_HEIGHT_SHARE)
    cost = np.where((distance <= limit) & plausible, distance, 1e9)
    rows, cols = linear_sum_assignment(cost)
    ok = cost[rows, cols] < 1e8
    return rows[ok].astype(np.int64), cols[ok].astype(np.int64)


@dataclass(frozen=True)
class Scores:
    """Detection, DBH and height figures over the true trees of a region."""

    n_truth: int
    f1: float
    recall: dict[str, float]
    dbh_measured_share: float
    dbh_rmse_cm: float
    height_rmse_m: dict[str, float]
    height_bias_m: dict[str, float]
    #: share of the detections there paired with a true tree (a tree found twice: one not)
    precision: float = float("nan")

    def line(self) -> str:
        recall = ", ".join(f"{k} {v:.3f}" for k, v in self.recall.items())
        height = ", ".join(
            f"{k} {self.height_rmse_m[k]:.2f} ({self.height_bias_m[k]:+.2f})" for k in KINDS
        )
        return (
            f"{self.n_truth} trees: F1 {self.f1:.3f}; recall {recall}; DBH measured "
            f"{self.dbh_measured_share:.3f}, RMSE {self.dbh_rmse_cm:.2f} cm; height RMSE "
            f"(bias) {height} m"
        )


def scores(found: pd.DataFrame, truth: pd.DataFrame, inside: object) -> Scores:
    """Figures over the true trees standing in ``inside(x, y)`` (and the detections
    there): F1, recall per kind, share of paired trees with a measured DBH and its RMSE,
    height RMSE and bias per kind."""
    rows, cols = pair(found, truth)
    t_in = inside(truth["x"].to_numpy(), truth["y"].to_numpy())  # type: ignore[operator]
    f_in = inside(found["x"].to_numpy(), found["y"].to_numpy())  # type: ignore[operator]
    paired_truth = np.zeros(len(truth), dtype=bool)
    paired_truth[cols] = True
    paired_found = np.zeros(len(found), dtype=bool)
    paired_found[rows] = True
    tp = int((t_in & paired_truth).sum())
    fn = int(t_in.sum()) - tp
    fp = int((f_in & ~paired_found).sum())
    kinds = truth["kind"].to_numpy()
    recall = {k: float(paired_truth[t_in & (kinds == k)].mean()) for k in KINDS}
    keep = t_in[cols]
    f, t = found.iloc[rows[keep]], truth.iloc[cols[keep]]
    dbh = f["dbh_m"].to_numpy(dtype=np.float64)
    source = f["dbh_source"].to_numpy() if "dbh_source" in f.columns else None
    measured = np.isfinite(dbh) if source is None else source == "measured"
    dbh_err = (dbh - t["dbh"].to_numpy())[measured] * 100.0
    height_err = f["height_m"].to_numpy() - t["height"].to_numpy()
    kind = t["kind"].to_numpy()
    return Scores(
        n_truth=int(t_in.sum()),
        f1=2 * tp / (2 * tp + fp + fn),
        recall=recall,
        dbh_measured_share=float(measured.mean()),
        dbh_rmse_cm=float(np.sqrt(np.mean(dbh_err**2))),
        height_rmse_m={k: float(np.sqrt(np.mean(height_err[kind == k] ** 2))) for k in KINDS},
        height_bias_m={k: float(np.mean(height_err[kind == k])) for k in KINDS},
        precision=tp / max(tp + fp, 1),
    )


def inset_of(bounds: tuple[float, float, float, float], margin: float) -> object:
    """``inside(x, y)`` for the stand ``bounds`` less ``margin`` m on every side (trees at
    the survey's edge are seen from one side only)."""
    x0, y0, x1, y1 = bounds

    def inside(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return (x > x0 + margin) & (x < x1 - margin) & (y > y0 + margin) & (y < y1 - margin)

    return inside
