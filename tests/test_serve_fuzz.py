"""Every route of both OpenAPI documents (the service's ``/openapi.json`` and the OGC API's
``/ogc/api``) against a live server, with hostile values in each path and query parameter
(huge and negative integers, inf, nan, empty, long and unicode text, coordinates out of
range) mixed with real ones: no answer is a 5xx, and the server keeps answering."""

from __future__ import annotations

import re
import string
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

TOKEN = "fuzz-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
#: Texts that broke, or could break, a parser of numbers, dates, boxes, names or paths.
HOSTILE = [
    "",
    " ",
    "0",
    "-0",
    "-1",
    "1.5",
    "1e309",
    "-1e309",
    "inf",
    "-inf",
    "Infinity",
    "nan",
    "NaN",
    "1" * 400,
    "9" * 4400,
    "18446744073709551616",
    "-9223372036854775809",
    "100000000000000000000",
    "9999999999999999999999999999999999999999",
    "0x10",
    "1_000",
    "\u0663",
    "\uff11\uff12",
    "+1",
    "1,2",
    "-1,-100,1,100",
    "-181,-91,181,91",
    "1,2,3",
    "nan,nan,nan,nan",
    "inf,0,1,1",
    "1e308,-1e308,1e308,1e308",
    "1,1,0,0",
    "0,0,1,1,1,1",
    "true",
    "false",
    "null",
    "[]",
    "{}",
    "'",
    '"',
    "' OR 1=1 --",
    "\x00",
    "%00",
    "\n",
    "../../etc/passwd",
    "..",
    ".",
    "/",
    "\\",
    "~",
    "*",
    "\u00e9t\u00e9",
    "\U0001f332" * 40,
    "x" * 2000,
    "2024-13-45",
    "2024-02-30T25:61:00Z",
    "../..",
    "9999-12-31/0001-01-01",
    "1_000000001",
    "99999999999999_000000000",
    "1_1",
    "0,0,0,0,0,0,2",
    "http://www.opengis.net/def/crs/EPSG/0/999999",
    "EPSG:4326",
    "<>",
]
#: The default run's sweep: the kinds of value that answered 500 (a huge integer, an
#: infinity, a latitude out of range) and a negative; every parameter of every route gets
#: each of them (the random cases draw from all of :data:`HOSTILE`, the slow run sweeps it).
SHARPEST = ["-1", "1e309", "99999999999999999999999", "-181,-91,181,91"]


@dataclass(frozen=True)
class Route:
    """One operation: method, URL template (absolute), its path and query parameters."""

    method: str
    url: str
    path_params: tuple[str, ...]
    query_params: tuple[str, ...]
    body: bytes | None

    def __str__(self) -> str:
        return f"{self.method} {self.url}"


def _routes(document: dict[str, Any], base: str) -> list[Route]:
    """The operations of an OpenAPI document served under ``base``."""
    found = []
    for template, item in document["paths"].items():
        for method, operation in item.items():
            if method not in ("get", "head", "post", "put", "delete") or not isinstance(
                operation, dict
            ):
                continue
            if "text/event-stream" in operation.get("responses", {}).get("200", {}).get(
                "content", {}
            ):
                continue  # an endless stream (tests/test_serve_events.py)
            params = operation.get("parameters", [])
            body = b"x" if "requestBody" in operation else None
            found.append(
                Route(
                    method.upper(),
                    base + template,
                    tuple(p["name"] for p in params if p["in"] == "path"),
                    tuple(p["name"] for p in params if p["in"] == "query"),
                    body,
                )
            )
    return found


@pytest.fixture(scope="module")
def served(
    enriched_catalog: Path, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[str, list[Route], dict[str, list[str]]]]:
    """A live server on the shared catalog (writes allowed, into a temporary missions
    folder: the fuzz creates no mission), its routes and real values of its parameters."""
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    missions = tmp_path_factory.mktemp("fuzz-inbox")
    with running(create_app(enriched_catalog, token=TOKEN, missions=missions)) as server:
        base = server.base_url
        assert base is not None
        with httpx.Client(timeout=30) as client:
            service = client.get(f"{base}/openapi.json").json()
            ogc = client.get(f"{base}/ogc/api").json()
            routes = _routes(service, base) + _routes(ogc, ogc["servers"][0]["url"])
            yield base, routes, _real_values(client, base)


def _real_values(client: httpx.Client, base: str) -> dict[str, list[str]]:
    """Valid values of the parameters, so hostile ones also reach deep into the routes."""
    collections = [c["id"] for c in client.get(f"{base}/ogc/collections").json()["collections"]]
    names = [m["name"] for m in client.get(f"{base}/missions").json()["missions"]]
    config = client.get(f"{base}/viewer/config.json").json()
    epochs = [e["label"] for e in config["epochs"]]
    payloads = client.get(f"{base}/missions/{names[0]}/payloads").json()["payloads"]
    stamps = [f"{p['stamp_ns'] // 10**9}_{p['stamp_ns'] % 10**9:09d}" for p in payloads[:3]]
    cells = client.get(f"{base}/ogc/collections/cells/items", params={"limit": 3}).json()
    files = [f["path"] for f in client.get(f"{base}/files").json()["files"][:5]]
    return {
        "collection_id": collections,
        "collectionId": collections,
        "name": names,
        "epoch": epochs,
        "stamp": stamps,
        "relative": files,
        "cell_id": [str(f["properties"].get("cell_id")) for f in cells["features"]],
        "feature_id": ["1", "2"],
        "featureId": ["1", "2"],
        "payload": ["1", "65536"],
        "tree": ["1"],
        "type": ["point_cloud", "gnss"],
        "frame": ["crs", "map", "base"],
        "x": ["0", "5.5"],
        "y": ["0", "-3"],
        "lat": ["51.77"],
        "lon": ["-1.34"],
        "bbox": ["-1.4,51.7,-1.3,51.8"],
        "datetime": ["2024-05-14", "2024-01-01/.."],
        "limit": ["2"],
        "offset": ["1"],
        "k": ["2"],
        "exact": ["false"],
        "format": ["pcd"],
        "crs": ["http://www.opengis.net/def/crs/OGC/1.3/CRS84"],
    }


def _hostile() -> st.SearchStrategy[str]:
    return st.one_of(
        st.sampled_from(HOSTILE),
        st.integers().map(str),
        st.integers(min_value=2**62, max_value=10**30).map(lambda v: str(v * (-1) ** v)),
        st.floats().map(repr),
        st.text(max_size=40),
        st.text(string.digits + ",.-e", max_size=30),
    )


def _request(route: Route, values: dict[str, str]) -> tuple[str, dict[str, str]]:
    """The URL and query of ``route`` with ``values`` (path parameters quoted)."""
    url = route.url
    for name in route.path_params:
        safe = "/" if name == "relative" else ""  # a path parameter of its own
        url = url.replace("{" + name + "}", quote(values.get(name, ""), safe=safe))
    return url, {k: v for k, v in values.items() if k in route.query_params}


def _check(client: httpx.Client, route: Route, values: dict[str, str]) -> None:
    url, params = _request(route, values)
    answer = client.request(route.method, url, params=params, content=route.body, headers=AUTH)
    assert answer.status_code < 500, f"{route} {url} {params}: {answer.text[:300]}"


def _fuzz(client: httpx.Client, route: Route, real: dict[str, list[str]], examples: int) -> int:
    """``examples`` requests of ``route``: each gives one parameter (drawn) a hostile value,
    and the others real values, hostile ones or none."""
    sent = 0
    names = [*route.path_params, *route.query_params]

    @settings(
        max_examples=examples,
        deadline=None,
        database=None,
        derandomize=True,
        suppress_health_check=list(HealthCheck),
    )
    @given(data=st.data())
    def case(data: st.DataObject) -> None:
        nonlocal sent
        target = data.draw(st.sampled_from(names), label="target") if names else None
        values = {}
        for name in names:
            real_ones = real.get(name, [])
            if name == target or not real_ones:
                choice = (
                    "hostile"
                    if name == target
                    else data.draw(st.sampled_from(["hostile", "none"]), label=f"{name} is")
                )
            else:
                choice = data.draw(st.sampled_from(["real", "hostile", "none"]), label=f"{name} is")
            if choice == "real":
                values[name] = data.draw(st.sampled_from(real_ones), label=name)
            elif choice == "hostile":
                values[name] = data.draw(_hostile(), label=name)
            elif name in route.path_params:
                values[name] = real_ones[0] if real_ones else ""
        _check(client, route, values)
        sent += 1

    case()
    return sent


def _sweep(
    client: httpx.Client,
    route: Route,
    real: dict[str, list[str]],
    hostile: list[str],
    seen: set[tuple[str, str, str]] | None = None,
) -> int:
    """Every value of ``hostile`` in every parameter of ``route``, the others real; with
    ``seen``, a parameter swept already in another collection's route of this kind is left
    to the random cases (the same code reads it)."""
    names = [*route.path_params, *route.query_params]
    valid = {n: real[n][0] for n in names if real.get(n)}
    kind = re.sub(r"/collections/[^/{]+", "/collections/*", route.url)
    if seen is not None:
        names = [n for n in names if (route.method, kind, n) not in seen]
        seen.update((route.method, kind, n) for n in names)
    for name in names:
        for value in hostile:
            _check(client, route, {**valid, name: value})
    return len(names) * len(hostile)


def _run(
    served: tuple[str, list[Route], dict[str, list[str]]], examples: int, *, sweep: bool = False
) -> None:
    base, routes, real = served
    start = time.monotonic()
    cases = 0
    seen: set[tuple[str, str, str]] = set()
    with httpx.Client(timeout=30) as client:
        for route in routes:
            if route.method == "POST" and route.url.endswith("/missions"):
                continue  # a JSON body, no parameters (tests/test_serve_edges.py)
            if sweep:
                cases += _sweep(client, route, real, HOSTILE)
            else:
                cases += _sweep(client, route, real, SHARPEST, seen)
            cases += _fuzz(client, route, real, examples)
            alive = client.get(f"{base}/ogc/conformance", timeout=5)
            assert alive.status_code == 200, f"unresponsive after {route}"
    took = time.monotonic() - start
    print(f"\nfuzz: {len(routes)} routes, {cases} cases, {took:.1f} s")
    assert len(routes) >= 40 and cases >= len(routes)


def test_hostile_parameters_never_answer_5xx(
    served: tuple[str, list[Route], dict[str, list[str]]],
) -> None:
    _run(served, examples=2)


@pytest.mark.slow
def test_hostile_parameters_never_answer_5xx_long(
    served: tuple[str, list[Route], dict[str, list[str]]],
) -> None:
    _run(served, examples=200, sweep=True)
