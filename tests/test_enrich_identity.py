"""One identity per tree across epochs (``tree_uid``): simulated re-surveys with known trees."""

from __future__ import annotations

import numpy as np
import pandas as pd

from standgrid.comparison.trees import match_trees
from standgrid.enrichment.identity import assign_tree_uids


def survey(rng: np.random.Generator, truth: pd.DataFrame, seen: np.ndarray) -> pd.DataFrame:
    """The trees a survey found: positions within 3 cm (stems), heights within 0.3 m."""
    found = truth[seen].reset_index(drop=True)
    return pd.DataFrame(
        {
            "tree_id": np.arange(len(found)) + 1000 * rng.integers(1, 9),
            "x": found["x"] + rng.normal(0, 0.03, len(found)),
            "y": found["y"] + rng.normal(0, 0.03, len(found)),
            "height_m": found["height_m"] + rng.normal(0, 0.3, len(found)),
            "truth": found["truth"],
        }
    )


def test_tree_uids_follow_trees_across_three_surveys() -> None:
    """A tree missed by the middle survey keeps its uid in the last; ingrowth gets new uids;
    a harvested tree's uid is never reused; re-enriching the middle epoch gives it the same
    uids again."""
    rng = np.random.default_rng(4)
    n = 400
    truth = pd.DataFrame(
        {
            "x": rng.uniform(0, 100, n),
            "y": rng.uniform(0, 100, n),
            "height_m": rng.uniform(5, 30, n),
            "truth": np.arange(n),
        }
    )
    missed = rng.random(n) < 0.05
    harvested = rng.random(n) < 0.1
    s1 = survey(rng, truth, np.ones(n, bool))
    s2 = survey(rng, truth, ~missed & ~harvested)
    grown = truth.assign(height_m=truth["height_m"] + 1.5)
    ingrowth = pd.DataFrame(
        {
            "x": rng.uniform(0, 100, 8),
            "y": rng.uniform(0, 100, 8),
            "height_m": rng.uniform(3, 5, 8),
            "truth": n + np.arange(8),
        }
    )
    s3 = survey(
        rng, pd.concat([grown, ingrowth], ignore_index=True), np.r_[~harvested, np.ones(8, bool)]
    )
    dates = {"2020": "2020-06-01", "2024": "2024-06-01", "2028": "2028-06-01"}
    uids = assign_tree_uids({"2020": s1, "2024": s2, "2028": s3}, dates, {})
    assert np.array_equal(uids["2020"], np.arange(1, n + 1))  # first survey: 1..n
    tables = {e: t.assign(tree_uid=uids[e]) for e, t in (("2020", s1), ("2024", s2), ("2028", s3))}
    # the same true tree has the same uid in every survey that found it
    first = dict(zip(tables["2020"]["truth"], tables["2020"]["tree_uid"], strict=True))
    for epoch in ("2024", "2028"):
        t = tables[epoch]
        old = t["truth"] < n
        assert (t.loc[old, "tree_uid"].to_numpy() == t.loc[old, "truth"].map(first)).all()
        assert t["tree_uid"].is_unique
    new = tables["2028"][tables["2028"]["truth"] >= n]
    assert len(new) == 8 and (new["tree_uid"] > n).all()
    # the middle epoch enriched again, against the two others: the same uids
    again = assign_tree_uids({"2024": s2}, dates, {"2020": tables["2020"], "2028": tables["2028"]})
    assert np.array_equal(again["2024"], uids["2024"])
    # compare by uid: the harvested trees are removed, every other is grown
    matches = match_trees(
        tables["2020"], tables["2028"], date_from="2020-06-01", date_to="2028-06-01", by_uid=True
    )
    counts = matches.counts()
    assert counts == {"grown": int((~harvested).sum()), "new": 8, "removed": int(harvested.sum())}
    geometric = match_trees(
        tables["2020"], tables["2028"], date_from="2020-06-01", date_to="2028-06-01"
    )
    assert geometric.counts() == counts
