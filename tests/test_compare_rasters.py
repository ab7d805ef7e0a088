"""CHM difference: exact values on aligned grids, refusal of misaligned ones, COG output."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine

from standgrid.comparison.rasters import NODATA, chm_difference
from standgrid.errors import FormatError, GridMismatchError, OutputExistsError

X0, Y0, RES = 500_000.0, 6_700_100.0, 0.5


def _write(
    path: Path,
    data: np.ndarray,
    *,
    left=X0,
    top=Y0,
    res=RES,
    crs="EPSG:32633",
    nodata: float | None = -1.0,
) -> Path:
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=data.shape[1],
        height=data.shape[0],
        count=1,
        dtype="float32",
        crs=crs,
        transform=Affine(res, 0.0, left, 0.0, -res, top),
        nodata=nodata,
    ) as dst:
        dst.write(data.astype(np.float32), 1)
    return path


def _ramp(h: int, w: int, scale: float = 1.0) -> np.ndarray:
    return scale * (np.arange(h * w, dtype=np.float64).reshape(h, w) % 97) / 4.0


def test_same_extent_difference_is_exact_and_a_cog(tmp_path):
    before = _ramp(40, 30)
    after = before + 1.25
    after[5, 7] = before[5, 7] - 3.0  # a felled tree
    before[0, 0] = -1.0  # nodata in "from"
    a = _write(tmp_path / "chm_2020.tif", before)
    b = _write(tmp_path / "chm_2024.tif", after)
    out = tmp_path / "compare" / "chm_diff.tif"
    result = chm_difference(a, b, out)

    assert result.path == out and out.exists()
    assert (result.width, result.height) == (30, 40)
    assert result.valid_pixels == 40 * 30 - 1
    with rasterio.open(out) as src:
        assert src.dtypes[0] == "float32"
        assert src.nodata == NODATA
        assert src.crs.to_epsg() == 32633
        assert src.transform == Affine(RES, 0.0, X0, 0.0, -RES, Y0)
        assert src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        diff = src.read(1)
        mask = src.read_masks(1)
    assert diff[0, 0] == NODATA and mask[0, 0] == 0
    expected = np.full((40, 30), 1.25)
    expected[5, 7] = -3.0
    valid = mask > 0
    np.testing.assert_allclose(diff[valid], expected[valid], atol=1e-5)
    assert result.mean_change_m == pytest.approx(float(expected[valid].mean()), abs=1e-9)
    assert not list(out.parent.glob(".*tmp"))  # no temporary left behind


def test_shifted_extents_intersection_and_union(tmp_path):
    before = _ramp(20, 20)
    # "to" raster starts 4 columns right and 2 rows down (whole pixels): aligned grid
    after = np.full((20, 20), 10.0)
    a = _write(tmp_path / "a.tif", before)
    b = _write(tmp_path / "b.tif", after, left=X0 + 4 * RES, top=Y0 - 2 * RES)

    inter = chm_difference(a, b, tmp_path / "inter.tif")
    assert (inter.width, inter.height) == (16, 18)
    assert inter.transform[2] == X0 + 4 * RES and inter.transform[5] == Y0 - 2 * RES
    with rasterio.open(tmp_path / "inter.tif") as src:
        diff = src.read(1)
    np.testing.assert_allclose(diff, 10.0 - before[2:, 4:], atol=1e-5)

    union = chm_difference(a, b, tmp_path / "union.tif", extent="union")
    assert (union.width, union.height) == (24, 22)
    assert union.valid_pixels == 16 * 18
    with rasterio.open(tmp_path / "union.tif") as src:
        assert src.bounds.left == X0 and src.bounds.top == Y0
        data = src.read(1, masked=True)
    assert data.mask[:2, :].all() and data.mask[:, :4].all()  # only "from" there
    assert data.mask[20:, :].all() and data.mask[:, 20:].all()  # only "to" there
    np.testing.assert_allclose(data[2:20, 4:20], 10.0 - before[2:, 4:], atol=1e-5)


def test_half_pixel_misalignment_is_refused(tmp_path):
    a = _write(tmp_path / "a.tif", _ramp(10, 10))
    b = _write(tmp_path / "b.tif", _ramp(10, 10), left=X0 + RES / 2)
    out = tmp_path / "diff.tif"
    with pytest.raises(GridMismatchError, match=r"not aligned.*0\.5.*pixels") as info:
        chm_difference(a, b, out)
    assert "a.tif" in str(info.value) and "b.tif" in str(info.value)
    assert not out.exists()


def test_different_resolution_or_crs_is_refused(tmp_path):
    a = _write(tmp_path / "a.tif", _ramp(10, 10))
    coarse = _write(tmp_path / "coarse.tif", _ramp(5, 5), res=1.0)
    other_crs = _write(tmp_path / "crs.tif", _ramp(10, 10), crs="EPSG:32632")
    with pytest.raises(GridMismatchError, match="pixel size"):
        chm_difference(a, coarse, tmp_path / "d1.tif")
    with pytest.raises(GridMismatchError, match="different CRS"):
        chm_difference(a, other_crs, tmp_path / "d2.tif")
    local = _write(tmp_path / "local.tif", _ramp(10, 10), crs=None)
    with pytest.raises(GridMismatchError, match="different CRS"):
        chm_difference(a, local, tmp_path / "d3.tif")
    # two rasters in the same local frame (no CRS) can be compared
    local_b = _write(tmp_path / "local_b.tif", _ramp(10, 10) + 1.0, crs=None)
    result = chm_difference(local, local_b, tmp_path / "d4.tif")
    assert result.crs is None and result.mean_change_m == pytest.approx(1.0, abs=1e-6)


def test_disjoint_rasters_and_bad_files_are_refused(tmp_path):
    a = _write(tmp_path / "a.tif", _ramp(10, 10))
    far = _write(tmp_path / "far.tif", _ramp(10, 10), left=X0 + 100.0)
    with pytest.raises(GridMismatchError, match="do not overlap"):
        chm_difference(a, far, tmp_path / "d.tif")
    junk = tmp_path / "junk.tif"
    junk.write_text("not a tiff")
    with pytest.raises(FormatError, match=r"junk\.tif"):
        chm_difference(a, junk, tmp_path / "d.tif")


def test_existing_output_needs_overwrite(tmp_path):
    a = _write(tmp_path / "a.tif", _ramp(10, 10))
    b = _write(tmp_path / "b.tif", _ramp(10, 10) + 2.0)
    out = tmp_path / "d.tif"
    chm_difference(a, b, out)
    with pytest.raises(OutputExistsError):
        chm_difference(b, a, out, overwrite=False)
    result = chm_difference(b, a, out)
    assert result.mean_change_m == pytest.approx(-2.0, abs=1e-5)


def test_nan_nodata_inputs(tmp_path):
    before = _ramp(8, 8)
    before[3, 3] = np.nan
    a = _write(tmp_path / "a.tif", before, nodata=np.nan)
    b = _write(tmp_path / "b.tif", before + 0.5, nodata=None)
    result = chm_difference(a, b, tmp_path / "d.tif")
    assert result.valid_pixels == 63
    with rasterio.open(tmp_path / "d.tif") as src:
        data = src.read(1, masked=True)
    assert data.mask[3, 3] and data.count() == 63
    np.testing.assert_allclose(data.compressed(), 0.5, atol=1e-6)
