"""Catalogs in object storage (standgrid.catalog.remote) against a real S3-compatible server
(moto_server on 127.0.0.1): the same catalog as on disk, kills during a commit, the lease."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner

from standgrid.catalog.remote import HEAD, LOCK, Lease, RemoteCatalog, catalog_at
from standgrid.cli import cli
from standgrid.errors import CatalogBusyError, CatalogConflictError, CatalogNotFoundError
from standgrid.storage import ObjectFolder
from tests.conftest import BUNDLED_MISSIONS, REPO_ROOT
from tests.s3_server import CREDENTIALS, moto_server, new_bucket

pytest.importorskip("obstore")
M1, M2 = sorted(p for p in BUNDLED_MISSIONS.iterdir() if p.is_dir())


def _digest_module():  # benchmarks/catalog_digest.py: what two identical runs share
    spec = importlib.util.spec_from_file_location(
        "catalog_digest", REPO_ROOT / "benchmarks" / "catalog_digest.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


digest_catalog = _digest_module().digest_catalog


@pytest.fixture(scope="module")
def endpoint() -> Iterator[str]:
    with moto_server() as url:
        yield url


@pytest.fixture
def s3(endpoint: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """``s3://<new bucket>/catalogs``, with the server's endpoint and credentials in the
    environment (as a user would set them) and working copies under ``tmp_path``."""
    for key, value in CREDENTIALS.items():
        monkeypatch.setenv(key, value)
    monkeypatch.setenv("AWS_ENDPOINT_URL", endpoint)
    monkeypatch.setenv("STANDGRID_WORK_DIR", str(tmp_path / "work"))
    return f"s3://{new_bucket(endpoint)}/catalogs"


def checkout(url: str, target: Path) -> Path:
    """The catalog at ``url`` as read by a reader, copied to ``target``."""
    import shutil

    with catalog_at(url, write=False) as root:
        shutil.copytree(root, target)
    return target


def tile(args: list[str]) -> None:
    result = CliRunner().invoke(cli, ["tile", *args, "-q"])
    assert result.exit_code == 0, result.output


@pytest.mark.slow
def test_a_catalog_on_s3_is_the_catalog_on_disk(s3: str, tmp_path: Path) -> None:
    url = f"{s3}/demo"
    for mission in (M1, M2):  # a new catalog, then a second epoch added to it
        tile([str(mission), "-o", str(tmp_path / "disk" / "demo")])
        tile([str(mission), "-o", url])
    on_disk = digest_catalog(tmp_path / "disk" / "demo")
    on_s3 = digest_catalog(checkout(url, tmp_path / "s3" / "demo"))
    assert len(on_disk) > 50 and on_s3 == on_disk  # tile bytes, index rows, VPCs, project

    remote = RemoteCatalog(url)
    head = remote.head()
    assert head is not None and head.generation == 2
    keys = [m["path"] for m in remote.folder.list()]
    generations = {k.split("/")[0] for k in keys if k.startswith("g")}
    assert generations == {head.root, *{g for g in generations if g != head.root}}
    assert len(generations) == 2  # the current one and the one before, for readers in flight
    lease = remote.folder.read(LOCK)  # the lease is given up: written back expired
    assert lease is not None and json.loads(lease[0])["expires"] == 0
    secret = CREDENTIALS["AWS_SECRET_ACCESS_KEY"].encode()
    for key in keys:  # credentials are never written to the catalog
        data = remote.folder.read(key)
        assert data is not None and secret not in data[0]

    status = CliRunner().invoke(cli, ["status", url, "--json"])
    assert status.exit_code == 0, status.output
    document = json.loads(status.stdout)
    assert document["catalog"] == url and sorted(document["epochs"]) == ["2024", "2028"]
    refused = CliRunner().invoke(cli, ["tile", str(M2), "-o", url, "--grid", "50"])
    assert refused.exit_code == 1 and "GridMismatchError" in refused.output
    assert f"{url}/catalog.json" in refused.output  # the catalog's URL, not a working copy
    assert "standgrid-catalog-" not in refused.output
    head_after = remote.head()
    assert head_after is not None and head_after.generation == 2  # nothing committed


@pytest.mark.slow
def test_missions_read_from_object_storage(s3: str, tmp_path: Path) -> None:
    folder = ObjectFolder.open(f"{s3}/missions/{M1.name}")
    for path in sorted(M1.rglob("*")):
        if path.is_file():
            folder.upload(path, path.relative_to(M1).as_posix())
    tile([f"{s3}/missions/{M1.name}", "-o", str(tmp_path / "from-s3")])
    tile([str(M1), "-o", str(tmp_path / "from-disk")])
    mine = digest_catalog(tmp_path / "from-s3")
    theirs = digest_catalog(tmp_path / "from-disk")
    assert mine.keys() == theirs.keys()
    tiles = [k for k in mine if k.startswith("tiles/")]
    assert tiles and all(mine[k] == theirs[k] for k in tiles)  # the same points, bit for bit


def test_a_url_without_a_catalog_is_a_typed_error(s3: str) -> None:
    with (
        pytest.raises(CatalogNotFoundError, match="no standgrid catalog here"),
        catalog_at(f"{s3}/nothing", write=False),
    ):
        pass
    result = CliRunner().invoke(cli, ["status", f"{s3}/nothing"])
    assert result.exit_code == 1 and "CatalogNotFoundError" in result.output
    assert "Traceback" not in result.output


def test_a_second_writer_waits_for_the_lease_then_gives_up(s3: str) -> None:
    url = f"{s3}/busy"
    holder = Lease(ObjectFolder.open(url), timeout=1).acquire()
    try:
        with (
            pytest.raises(CatalogBusyError, match="another writer holds the catalog"),
            catalog_at(url, write=True, lock_timeout=0.5),
        ):
            pass
    finally:
        holder.release()
    with catalog_at(url, write=True, lock_timeout=0.5):  # free again
        pass


@pytest.mark.slow
def test_a_commit_on_a_stale_head_is_refused(s3: str, tmp_path: Path) -> None:
    url = f"{s3}/stale"
    tile([str(M1), "-o", url])
    remote = RemoteCatalog(url)
    before = remote.head()
    assert before is not None
    stale_root = tmp_path / "work-stale"
    checkout(url, stale_root)
    (stale_root / "notes.txt").write_text("a change made on an old view")
    tile([str(M2), "-o", url])  # another writer commits meanwhile
    lease = Lease(remote.folder, timeout=5).acquire()
    try:
        with pytest.raises(CatalogConflictError, match="another writer committed first"):
            remote._commit(stale_root, before, remote.manifest(before), lease)
    finally:
        lease.release()
    head = remote.head()
    assert head is not None and head.generation == 2


_CHILD = """
import sys
from standgrid.cli import main
sys.argv = ["standgrid", "tile", sys.argv[1], "-o", sys.argv[2], "-q"]
main()
"""


@pytest.mark.parametrize(
    ("point", "landed"),
    [
        pytest.param("remote-before-switch", False, marks=pytest.mark.slow),
        pytest.param("remote-uploaded", False, marks=pytest.mark.slow),
        pytest.param("remote-switched", True, marks=pytest.mark.slow),
    ],
)
def test_a_kill_during_a_commit_leaves_the_old_or_the_new_catalog(
    s3: str, tmp_path: Path, point: str, landed: bool
) -> None:
    url = f"{s3}/killed"
    tile([str(M1), "-o", url])
    old = digest_catalog(checkout(url, tmp_path / "old" / "killed"))
    env = {**os.environ, "STANDGRID_CRASH_AT": point}
    child = subprocess.run(
        [sys.executable, "-c", _CHILD, str(M2), url], env=env, capture_output=True, timeout=300
    )
    assert child.returncode == -9, child.stderr.decode()[-2000:]  # SIGKILL at that point
    seen = digest_catalog(checkout(url, tmp_path / "seen" / "killed"))
    reference = tmp_path / "disk" / "killed"  # the catalog with both missions, on disk
    tile([str(M1), "-o", str(reference)])
    tile([str(M2), "-o", str(reference)])
    assert seen == (digest_catalog(reference) if landed else old)  # whole, never a mix
    remote = RemoteCatalog(url)
    assert remote.folder.read(LOCK) is not None  # the dead writer's lease is still there
    tile([str(M2), "-o", url])  # ... and taken over: its pid is dead on this host
    head = remote.head()
    assert head is not None and head.generation == (3 if landed else 2)
    roots = {m["path"].split("/")[0] for m in remote.folder.list() if m["path"][0] == "g"}
    assert len(roots) == 2  # the killed commit's half-written generation is gone
    if not landed:
        final = digest_catalog(checkout(url, tmp_path / "final" / "killed"))
        assert final == digest_catalog(reference)


@pytest.mark.slow
def test_head_is_what_readers_follow(s3: str) -> None:
    url = f"{s3}/head"
    tile([str(M1), "-o", url])
    remote = RemoteCatalog(url)
    found = remote.folder.read(HEAD)
    assert found is not None
    body = json.loads(found[0])
    assert body["generation"] == 1 and body["root"].startswith("g000001-")
    manifest = remote.manifest(remote.head())  # type: ignore[arg-type]
    assert "catalog.json" in manifest and "index.gpkg" in manifest
    for rel, entry in manifest.items():  # every file named is there, at its size
        data = remote.folder.read(f"{body['root']}/{rel}")
        assert data is not None and len(data[0]) == entry["size"]


@pytest.mark.slow
def test_run_on_s3_tiles_enriches_and_compares_as_on_disk(s3: str, tmp_path: Path) -> None:
    """The whole path (tile, enrich: DTM/CHM GeoTIFFs, trees, stands; compare) on the
    server gives the catalog it gives on disk: tiles, rasters and tables byte for byte."""
    url = f"{s3}/run"
    for target in (str(tmp_path / "disk" / "run"), url):
        result = CliRunner().invoke(cli, ["run", str(M1), str(M2), "-o", target, "-q"])
        assert result.exit_code == 0, result.output
    on_disk = digest_catalog(tmp_path / "disk" / "run")
    on_s3 = digest_catalog(checkout(url, tmp_path / "s3" / "run"))
    assert any(k.endswith(".tif") for k in on_disk) and any("tree_list" in k for k in on_disk)
    assert on_s3 == on_disk


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.slow
def test_workers_without_a_shared_folder_build_and_enrich_the_same_catalog(
    s3: str, tmp_path: Path, endpoint: str
) -> None:
    """A dask scheduler and two workers that cannot see this process's folders (each worker
    runs in its own mount namespace with an empty file system over them): the catalog,
    the missions and the tiles travel through the S3-compatible server only."""
    import shutil
    import time

    if shutil.which("unshare") is None or os.geteuid() != 0:
        pytest.skip("needs root and unshare(1) to hide this process's folders from workers")
    private = Path(os.environ["STANDGRID_WORK_DIR"])  # working copies, fetched missions
    private.mkdir(parents=True)
    (private / "marker").write_text("only the client sees this")
    probe = subprocess.run(
        [
            "unshare",
            "--mount",
            "--propagation",
            "private",
            "--",
            "sh",
            "-c",
            f"mount -t tmpfs none {private} && ! test -e {private}/marker",
        ],
        capture_output=True,
    )
    if probe.returncode != 0:
        pytest.skip(f"cannot hide a folder in a mount namespace here: {probe.stderr!r}")
    for mission in (M1, M2):
        folder = ObjectFolder.open(f"{s3}/missions/{mission.name}")
        for path in sorted(mission.rglob("*")):
            if path.is_file():
                folder.upload(path, path.relative_to(mission).as_posix())
    dask = str(Path(sys.executable).with_name("dask"))
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ}
    processes = [
        subprocess.Popen(
            [dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    ]
    try:
        for k in range(2):
            own = tmp_path / f"worker-{k}"
            own.mkdir()
            command = (
                f"mount -t tmpfs none {private} && exec {dask} worker {address} --nworkers 1 "
                f"--nthreads 2 --no-dashboard --local-directory {own}"
            )
            processes.append(
                subprocess.Popen(
                    ["unshare", "--mount", "--propagation", "private", "--", "sh", "-c", command],
                    env=env,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        from distributed import Client

        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=120)
            seen = client.run(lambda: os.path.exists(private / "marker"))
            assert list(seen.values()) == [False, False]  # they do not see our folders
        url = f"{s3}/cluster"
        missions = [f"{s3}/missions/{m.name}" for m in (M1, M2)]
        argv = ["tile", *missions, "-o", url, "--scheduler", address, "-q"]
        shared = subprocess.run(
            [str(Path(sys.executable).with_name("standgrid")), *argv],
            env=env,
            capture_output=True,
            timeout=600,
        )
        assert shared.returncode == 1  # workers told to read this process's folders cannot
        assert RemoteCatalog(url).head() is None
        t0 = time.perf_counter()
        result = CliRunner().invoke(cli, [*argv, "--no-shared-folder"])
        assert result.exit_code == 0, result.output
        seconds = time.perf_counter() - t0
        enrich = ["enrich", url, "--scheduler", address, "--no-shared-folder", "-q"]
        t0 = time.perf_counter()
        result = CliRunner().invoke(cli, enrich)
        assert result.exit_code == 0, result.output
        enrich_seconds = time.perf_counter() - t0
    finally:
        for process in processes[::-1]:
            process.terminate()
            process.wait(30)
    fetched = sorted(
        (p for p in (private / "standgrid-cache").glob("*/*") if p.is_dir()), key=lambda p: p.name
    )
    reference = tmp_path / "disk" / "cluster"  # the same missions, on disk, in this process
    tile([str(p) for p in fetched] + ["-o", str(reference)])
    enriched = CliRunner().invoke(cli, ["enrich", str(reference), "-q"])
    assert enriched.exit_code == 0, enriched.output
    on_s3 = digest_catalog(checkout(url, tmp_path / "s3" / "cluster"))
    assert on_s3 == digest_catalog(reference)  # tiles, rasters, tables, index: bit for bit
    assert any(k.startswith("tiles/") for k in on_s3) and any(k.endswith(".tif") for k in on_s3)
    keys = [m["path"] for m in RemoteCatalog(url).folder.list()]
    assert not any(k.startswith("_standgrid/outbox/") for k in keys)  # taken in, removed
    print(f"2 workers without a shared folder: tile {seconds:.1f} s, enrich {enrich_seconds:.1f} s")


@pytest.mark.slow
def test_nothing_but_generations_is_ever_deleted(s3: str) -> None:
    url = f"{s3}/shared-prefix"
    folder = ObjectFolder.open(url)
    folder.write("gis/roads.gpkg", b"a user's own file beside the catalog")
    folder.write("g000001-notmine/readme.txt", b"not a generation's name either")
    tile([str(M1), "-o", url])
    tile([str(M2), "-o", url])
    tile([str(M1), "-o", url])  # three commits: the first generation is collected
    keys = {m["path"] for m in folder.list()}
    assert {"gis/roads.gpkg", "g000001-notmine/readme.txt"} <= keys


def test_a_catalog_inside_its_missions_is_refused(s3: str) -> None:
    result = CliRunner().invoke(cli, ["tile", f"{s3}/missions/m1", "-o", f"{s3}/missions"])
    assert result.exit_code == 1 and "OutputOverlapsInputError" in result.output


def _first_line(proc: subprocess.Popen[str], timeout: float) -> str:
    """The process's first line of output, or the test fails (the process killed) when
    none comes within ``timeout`` s: a server that stalls never hangs the suite."""
    import threading

    lines: list[str] = []
    assert proc.stdout is not None
    reader = threading.Thread(target=lambda: lines.append(proc.stdout.readline()), daemon=True)  # type: ignore[union-attr]
    reader.start()
    reader.join(timeout)
    if not lines or not lines[0]:
        proc.kill()
        pytest.fail(f"no output from {proc.args} within {timeout} s")
    return lines[0]


@pytest.mark.slow  # a catalog tiled, a server started and stopped
def test_serve_a_catalog_in_object_storage(s3: str) -> None:
    import signal

    import httpx

    url = f"{s3}/served"
    tile([str(M1), "-o", url])
    remote = RemoteCatalog(url)
    head = remote.head()
    assert head is not None
    refused = CliRunner().invoke(
        cli, ["serve", url, "--port", "0"], env={"STANDGRID_TOKEN": "t" * 32}
    )
    assert refused.exit_code != 0 and "read-only" in refused.output
    command = [
        str(Path(sys.executable).with_name("standgrid")),
        "serve",
        url,
        "--port",
        "0",
        "--json",
    ]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        started = json.loads(_first_line(proc, timeout=120))
        assert started["catalog"] == url and started["writes"] is False
        base = started["service"].rstrip("/")
        files = httpx.get(f"{base}/files", timeout=30).json()["files"]
        tile_entry = next(f for f in files if f["path"].startswith("tiles/"))
        stored = remote.folder.read(f"{head.root}/{tile_entry['path']}")
        assert stored is not None and tile_entry["size"] == len(stored[0])
        part = httpx.get(tile_entry["href"], headers={"Range": "bytes=100-299"}, timeout=30)
        assert part.status_code == 206 and part.content == stored[0][100:300]
        cells = httpx.get(f"{base}/ogc/collections/cells/items?limit=5", timeout=30)
        assert cells.status_code == 200 and cells.json()["features"]
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=30)


@pytest.mark.realdata
@pytest.mark.slow
def test_a_plain_scan_in_object_storage_is_tiled_into_a_catalog_there(
    s3: str, tmp_path: Path
) -> None:
    from tests.conftest import real_file

    scan = real_file("als/las_chablais3.laz")
    ObjectFolder.open(f"{s3}/scans").upload(scan, scan.name)
    options = ["--date", "2019-07-01", "-q"]
    tile([f"{s3}/scans/{scan.name}", "-o", f"{s3}/als", *options])
    tile([str(scan), "-o", str(tmp_path / "disk" / "als"), *options])
    on_s3 = digest_catalog(checkout(f"{s3}/als", tmp_path / "s3" / "als"))
    on_disk = digest_catalog(tmp_path / "disk" / "als")
    tiles = sorted(k for k in on_disk if k.startswith("tiles/"))
    assert tiles and [on_s3.get(k) for k in tiles] == [on_disk[k] for k in tiles]
    missing = CliRunner().invoke(cli, ["tile", f"{s3}/scans/nothing.laz", "-o", f"{s3}/x"])
    assert missing.exit_code == 1 and "StorageError" in missing.output
    assert "nothing.laz" in missing.output and "Traceback" not in missing.output


@pytest.mark.slow
def test_a_stac_client_walks_a_generation_straight_from_the_server(s3: str, endpoint: str) -> None:
    """Plain HTTP against the S3-compatible server, no standgrid in between: HEAD.json
    names the generation, its stac/catalog.json leads to every tile and raster."""
    import boto3
    import httpx
    import pystac

    url = f"{s3}/stac"
    tile([str(M1), "-o", url])
    bucket = url.removeprefix("s3://").split("/")[0]
    policy = {  # published for anyone to read, as a STAC catalog is
        "Version": "2012-10-17",
        "Statement": [
            {
                "Effect": "Allow",
                "Principal": "*",
                "Action": "s3:GetObject",
                "Resource": f"arn:aws:s3:::{bucket}/*",
            }
        ],
    }
    boto3.client("s3", endpoint_url=endpoint).put_bucket_policy(
        Bucket=bucket, Policy=json.dumps(policy)
    )
    base = f"{endpoint}/{url.removeprefix('s3://')}"
    head = httpx.get(f"{base}/{HEAD}", timeout=30).json()
    root = pystac.Catalog.from_file(f"{base}/{head['root']}/stac/catalog.json")
    items = list(root.get_items(recursive=True))
    tiles = [i for i in items if "pc:count" in i.properties]
    assert tiles and len(tiles) == len(
        [
            k
            for k in RemoteCatalog(url).manifest(RemoteCatalog(url).head())
            if k.startswith("tiles/")
        ]  # type: ignore[arg-type]
    )
    for item in tiles[:5]:
        for asset in item.assets.values():
            href = asset.get_absolute_href() or ""  # a ranged read of each, anonymous
            answer = httpx.get(href, headers={"Range": "bytes=0-3"}, timeout=30)
            assert answer.status_code == 206 and len(answer.content) == 4, href


@pytest.mark.slow
def test_a_comparison_against_a_catalog_in_object_storage_goes_stale_with_it(
    s3: str, tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """``compare --other s3://…`` reads that catalog's current generation and records its
    URL; ``status`` reads that URL's HEAD to tell when the epoch it read changed."""
    import shutil

    from standgrid.comparison.options import CompareOptions
    from standgrid.pipeline.compare import compare_epochs
    from standgrid.pipeline.status import catalog_status
    from tests.pipeline_fixtures import MISSIONS, copy_catalog, enriched_pair

    pair = enriched_pair(tmp_path_factory)
    url = f"{s3}/other"
    with catalog_at(url, write=True) as root:  # an existing catalog, published there
        shutil.copytree(pair.path, root)
    here = copy_catalog(pair.path, tmp_path / "here")
    report = compare_epochs(here, CompareOptions("2024", "2028", other_catalog=url))
    assert report.trees and report.outputs
    key = "2024__2028"
    entry = json.loads((here / "catalog.json").read_text())["comparisons"][key]
    assert entry["other_catalog"] == url and entry["other_epoch"]["enrichment"]
    assert catalog_status(here)["comparisons"][key]["state"] == "present"
    tile([str(BUNDLED_MISSIONS / MISSIONS["2028"]), "-o", url])  # re-tiled there
    seen = catalog_status(here)["comparisons"][key]
    assert seen["state"] == "stale" and "re-tiled" in seen["reason"] and url in seen["reason"]


@pytest.mark.parametrize("body", [b"not json", b"[1, 2]", b'{"expires": "soon", "pid": "x"}'])
def test_a_damaged_lease_is_taken_over(s3: str, body: bytes) -> None:
    url = f"{s3}/damaged-lease"
    folder = ObjectFolder.open(url)
    folder.write(LOCK, body)
    with catalog_at(url, write=True, lock_timeout=1):
        found = folder.read(LOCK)
        assert found is not None and json.loads(found[0])["pid"] == os.getpid()
    found = folder.read(LOCK)
    assert found is not None and json.loads(found[0]).get("released") is True


@pytest.mark.parametrize(
    ("head", "files"),
    [
        ({"generation": 1, "root": "../../outside"}, {}),
        ({"generation": 1, "root": "g000001-0123abcd"}, {"../escape.txt": None}),
        ({"generation": 1, "root": "g000001-0123abcd"}, {"/etc/escape": None}),
        ({"generation": "one", "root": "g000001-0123abcd"}, {}),
    ],
)
def test_a_hostile_head_or_manifest_is_refused_before_any_file_is_written(
    s3: str, tmp_path: Path, head: dict[str, object], files: dict[str, None]
) -> None:
    from standgrid.errors import StorageError

    url = f"{s3}/hostile"
    folder = ObjectFolder.open(url)
    folder.write(HEAD, json.dumps(head).encode())
    manifest = {rel: {"size": 5, "sha256": "0" * 64} for rel in files}
    if ".." not in str(head["root"]):  # (obstore refuses to write such a key at all)
        body = json.dumps({"files": manifest}).encode()
        folder.write(f"_standgrid/manifests/{head['root']}.json", body)
    with (
        pytest.raises(StorageError, match=r"not a standgrid|is no generation"),
        catalog_at(url, write=False),
    ):
        pass
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]  # nothing written, anywhere
    assert not Path("/etc/escape").exists()


def test_a_fetched_mission_follows_its_objects(s3: str, tmp_path: Path) -> None:
    """A mission fetched from object storage is refreshed by size and ETag (a file replaced
    by one of the same size too), loses the files whose objects are gone, and keeps its
    URL as its source."""
    from standgrid.storage.objects import fetched_folder, source_of

    url = f"{s3}/missions/m"
    folder = ObjectFolder.open(url)
    folder.write("poses.csv", b"0,1,2\n")
    folder.write("clouds/a.pcd", b"points a")
    folder.write("clouds/b.pcd", b"points b")
    local = fetched_folder(url)
    assert (local / "clouds" / "b.pcd").read_bytes() == b"points b"
    assert source_of(local) == url and source_of(local / "clouds") == f"{url}/clouds"
    folder.write("poses.csv", b"9,9,9\n")  # the same size, new content
    folder.delete(["clouds/b.pcd"])
    again = fetched_folder(url)
    assert again == local and (local / "poses.csv").read_bytes() == b"9,9,9\n"
    assert not (local / "clouds" / "b.pcd").exists() and (local / "clouds" / "a.pcd").exists()
    assert not list(local.rglob("*.part"))


def test_a_conditional_write_without_an_etag_is_refused(s3: str) -> None:
    from standgrid.errors import StorageError

    folder = ObjectFolder.open(f"{s3}/etag")
    folder.write("x", b"1")
    with pytest.raises(StorageError, match="no ETag"):
        folder.write("x", b"2", if_match=None)
    found = folder.read("x")
    assert found is not None and found[0] == b"1"


@pytest.mark.parametrize(
    "url", ["s3://user:secret@bucket/p", "s3://bucket/p?X-Amz-Signature=abc", "s3://bucket/../p"]
)
def test_credentials_or_dots_in_a_url_are_refused(url: str) -> None:
    from standgrid.errors import StorageError

    with pytest.raises(StorageError) as caught:
        ObjectFolder.open(url)
    assert "secret" not in str(caught.value) and "abc" not in str(caught.value)


def test_an_unknown_aws_profile_is_a_typed_error(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    pytest.importorskip("boto3")
    monkeypatch.delenv("AWS_ACCESS_KEY_ID", raising=False)
    monkeypatch.setenv("AWS_PROFILE", "standgrid-no-such-profile")
    monkeypatch.setenv("AWS_CONFIG_FILE", str(tmp_path / "config"))
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", str(tmp_path / "credentials"))
    result = CliRunner().invoke(cli, ["status", "s3://bucket/catalog"])
    assert result.exit_code == 1 and "StorageError" in result.output
    assert "standgrid-no-such-profile" in result.output and "Traceback" not in result.output
    assert result.output.count("s3://bucket/catalog") == 1
