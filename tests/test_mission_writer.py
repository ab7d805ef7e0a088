"""write_mission: canonical layout, atomic, and reading back gives an equal mission."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mission_factory import make_graph, make_mission

from standgrid.errors import MissionNotFoundError, OutputExistsError
from standgrid.geometry import pose_matrix
from standgrid.mission.model import Mission
from standgrid.mission.opening import open_mission
from standgrid.mission.writer import write_mission


def assert_equal_missions(a: Mission, b: Mission) -> None:
    assert [p.stamp for p in a.payloads] == [p.stamp for p in b.payloads]
    assert a.graph is not None and b.graph is not None
    assert [v.stamp for v in a.graph.vertices.values()] == [
        v.stamp for v in b.graph.vertices.values()
    ]
    np.testing.assert_allclose(b.graph.poses, a.graph.poses, rtol=0, atol=1e-12)
    assert b.graph.edge_counts() == a.graph.edge_counts()
    for pa, pb in zip(a.payloads, b.payloads, strict=True):
        ca, cb = a.load_payload(pa, "map"), b.load_payload(pb, "map")
        np.testing.assert_allclose(cb.xyz, ca.xyz, rtol=0, atol=1e-9)
        assert set(ca.fields) == set(cb.fields)
        for name in ca.fields:
            np.testing.assert_array_equal(cb.fields[name], ca.fields[name])
        assert pa.layers.keys() == pb.layers.keys()
    for log in ("gnss", "imu"):
        la, lb = getattr(a, log), getattr(b, log)
        assert (la is None) == (lb is None)
        if la is not None:
            np.testing.assert_array_equal(lb.stamps_ns, la.stamps_ns)
    if a.gnss is not None:
        np.testing.assert_array_equal(b.gnss.lat, a.gnss.lat)  # type: ignore[union-attr]
        np.testing.assert_array_equal(b.gnss.quality, a.gnss.quality)  # type: ignore[union-attr]
    if a.imu is not None:
        np.testing.assert_array_equal(b.imu.gyro, a.imu.gyro)  # type: ignore[union-attr]
    assert a.metadata == b.metadata
    assert [(i.camera, i.stamp) for i in a.images] == [(i.camera, i.stamp) for i in b.images]


def test_round_trip(tmp_path: Path) -> None:
    syn = make_mission(
        tmp_path / "in", gnss=True, imu=True, cameras=("front",), fields=("intensity", "curvature")
    )
    original = open_mission(syn.path)
    out = write_mission(original, tmp_path / "out" / syn.path.name)
    for name in ("metadata.yaml", "slam_pose_graph.g2o", "slam_poses.csv", "gnss/fixes.txt"):
        assert (out / name).is_file(), name
    assert sorted(p.name for p in (out / "payload_clouds").iterdir()) == sorted(
        s.filename("cloud", "pcd") for s in syn.stamps
    )
    assert assert_equal_missions(original, open_mission(out)) is None
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temporary left


def test_round_trip_from_map_frame_clouds(tmp_path: Path) -> None:
    syn = make_mission(tmp_path / "in", cloud_folder="payload_clouds_in_map")
    original = open_mission(syn.path)
    out = write_mission(original, tmp_path / "out")
    back = open_mission(out)
    assert all(p.frame == "base" for p in back.payloads)
    assert_equal_missions(original, back)
    np.testing.assert_allclose(
        back.load_payload(back.payloads[0], "base").xyz, syn.clouds[syn.stamps[0]].xyz, atol=1e-9
    )


def test_realigned_view_is_written_with_its_graph(tmp_path: Path) -> None:
    syn = make_mission(tmp_path / "in")
    m = open_mission(syn.path)
    correction = pose_matrix([5.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    view = m.with_graph(make_graph(syn.stamps, correction @ syn.poses))
    back = open_mission(write_mission(view, tmp_path / "out"))
    np.testing.assert_allclose(back.graph.poses[:, 0, 3], syn.poses[:, 0, 3] + 5.0, atol=1e-12)  # type: ignore[union-attr]
    assert_equal_missions(view, back)


def test_overwrite_and_failure_leave_no_partial_output(tmp_path: Path) -> None:
    syn = make_mission(tmp_path / "in")
    m = open_mission(syn.path)
    out = write_mission(m, tmp_path / "out")
    with pytest.raises(OutputExistsError):
        write_mission(m, out)
    # a failing write (a cloud file vanished) keeps the previous output untouched
    fresh = open_mission(syn.path)
    (syn.path / "payload_clouds" / syn.stamps[-1].filename("cloud", "pcd")).unlink()
    with pytest.raises(MissionNotFoundError):
        write_mission(fresh, out, overwrite=True)
    assert len(list((out / "payload_clouds").iterdir())) == 5
    assert [p.name for p in out.parent.iterdir() if p.name.startswith(".")] == []
    # overwriting replaces a mission folder only, never a folder of other things
    other = tmp_path / "documents"
    other.mkdir()
    (other / "thesis.tex").write_text("mine")
    with pytest.raises(OutputExistsError, match="not a mission folder"):
        write_mission(open_mission(out), other, overwrite=True)
    assert [p.name for p in other.iterdir()] == ["thesis.tex"]
    # a folder with a mission's parts and other things is not a mission folder either
    (other / "metadata.yaml").write_text("name: notes\n")
    with pytest.raises(OutputExistsError, match="not a mission folder"):
        write_mission(open_mission(out), other, overwrite=True)
    assert sorted(p.name for p in other.iterdir()) == ["metadata.yaml", "thesis.tex"]


def test_scans_written_only_on_request(tmp_path: Path) -> None:
    syn = make_mission(tmp_path / "in", n_nodes=3, cloud_folder="individual_clouds")
    m = open_mission(syn.path)
    plain = open_mission(write_mission(m, tmp_path / "plain"))
    assert plain.scans == [] and plain.payloads == []
    full = open_mission(write_mission(m, tmp_path / "full", include_scans=True))
    assert [s.stamp for s in full.scans] == syn.stamps
    np.testing.assert_allclose(
        full.load_payload(full.scans[1], "map").xyz,
        m.load_payload(m.scans[1], "map").xyz,
        atol=1e-9,
    )


def test_per_payload_logs_named_by_payload_stamp_every_sample_once(tmp_path: Path) -> None:
    from standgrid.mission.sensors import read_gnss, read_imu
    from standgrid.simulate import simulate_mission
    from standgrid.stamps import stamp_from_filename

    sim = simulate_mission(tmp_path / "sim", seed=4, epoch=1, area=50.0, points_per_payload=500)
    assert sim.mission_dir is not None
    original = open_mission(sim.mission_dir)
    assert original.gnss is not None and original.imu is not None
    out = write_mission(original, tmp_path / "out")
    payload_ns = np.array(sorted(p.stamp.ns for p in original.payloads), dtype=np.int64)
    mids = payload_ns[:-1] + (payload_ns[1:] - payload_ns[:-1]) // 2
    lower = np.concatenate([[np.iinfo(np.int64).min], mids])
    upper = np.concatenate([mids, [np.iinfo(np.int64).max]])
    for sub, reader, log in (("gnss", read_gnss, original.gnss), ("imu", read_imu, original.imu)):
        files = sorted((out / "payloads" / sub).iterdir())
        stamps = [stamp_from_filename(f.name)[1].ns for f in files]  # type: ignore[index]
        assert stamps == payload_ns.tolist(), sub
        parts = [reader(f) for f in files]
        for k, part in enumerate(parts):  # each sample lies in its payload's window
            assert ((part.stamps_ns >= lower[k]) & (part.stamps_ns < upper[k])).all(), sub
        written = np.concatenate([p.stamps_ns for p in parts])
        np.testing.assert_array_equal(written, log.stamps_ns)  # all kept, once, in order
    back = open_mission(out)
    assert_equal_missions(original, back)
