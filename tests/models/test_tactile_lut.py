"""GelSight lookup table: frames, analytic sphere gradients, the table, files and their errors."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from models.tactile.lut import (
    FORMAT_VERSION,
    DataPack,
    GelSightLUT,
    GelSightLUTError,
    build_lut,
    build_lut_from_datapack,
    check_image,
    default_datapack_path,
    load_datapack,
    load_press_folder,
    parse_frames,
    read_image_bgr,
    sphere_gradients,
)

FEW_FRAMES = [0, 2, 4, 6]


@pytest.fixture(scope="module")
def pack() -> DataPack:
    return load_datapack(default_datapack_path())


@pytest.fixture(scope="module")
def small_calibration(pack: DataPack) -> GelSightLUT:
    return build_lut_from_datapack(pack, FEW_FRAMES)


def save_png(path: Path, image_bgr: np.ndarray) -> Path:
    Image.fromarray(np.ascontiguousarray(image_bgr[:, :, ::-1])).save(path)
    return path


def test_datapack_is_the_real_presses(pack: DataPack) -> None:
    assert pack.images_bgr.shape == (48, 480, 640, 3)
    assert pack.reference_bgr.shape == (480, 640, 3)
    press = pack.press(5)
    assert press.name == "5"
    assert press.centre_px == tuple(pack.centres_px[5])
    assert press.radius_px == pack.radii_px[5]


def test_parse_frames() -> None:
    assert parse_frames("all", 4) == [0, 1, 2, 3]
    assert parse_frames("even", 5) == [0, 2, 4]
    assert parse_frames("odd", 5) == [1, 3]
    assert parse_frames("3, 1,", 5) == [3, 1]
    with pytest.raises(GelSightLUTError, match="empty"):
        parse_frames("", 5)
    with pytest.raises(GelSightLUTError, match="empty"):
        parse_frames("odd", 1)
    with pytest.raises(GelSightLUTError, match=r"\[7\] out of range"):
        parse_frames("1,7", 5)
    with pytest.raises(GelSightLUTError, match="comma-separated"):
        parse_frames("1-3", 5)


def test_sphere_gradients_are_the_cap_slopes() -> None:
    ball_px, centre = 50.0, (30.0, 20.0)
    gx, gy, inside = sphere_gradients((40, 60), centre, 35.0, ball_px)
    # At (col 60-1, row 20) the cap falls away along +x with slope rho / sqrt(R^2 - rho^2).
    rho = 59 - centre[0]
    assert gx[20, 59] == pytest.approx(-rho / np.sqrt(ball_px**2 - rho**2))
    assert gy[20, 59] == 0.0
    assert gx[20, 30] == 0.0 and gy[20, 30] == 0.0  # the apex is flat
    assert gy[39, 30] == pytest.approx(-19 / np.sqrt(ball_px**2 - 19**2))
    assert not inside[0, 0] and gx[0, 0] == 0.0
    # Finite differences of the analytic height agree with the analytic slopes.
    rows, cols = np.indices((40, 60), dtype=float)
    height = np.sqrt(ball_px**2 - (cols - centre[0]) ** 2 - (rows - centre[1]) ** 2)
    d_rows, d_cols = np.gradient(height)
    core = inside & ((cols - centre[0]) ** 2 + (rows - centre[1]) ** 2 < 30**2)
    core[[0, -1], :] = core[:, [0, -1]] = False  # np.gradient is one-sided there
    np.testing.assert_allclose(gx[core], d_cols[core], rtol=5e-3, atol=1e-4)
    np.testing.assert_allclose(gy[core], d_rows[core], rtol=5e-3, atol=1e-4)


def test_calibration_table_and_metadata(small_calibration: GelSightLUT) -> None:
    calibration = small_calibration
    assert calibration.image_shape == (480, 640)
    assert calibration.tile_count == 48 and calibration.levels == 17
    assert calibration.table_gx.dtype == np.float32
    assert calibration.table_gx.shape == (48 * 17**3,)
    assert calibration.frames == ("0", "2", "4", "6")
    meta = calibration.metadata()
    assert meta["version"] == FORMAT_VERSION
    assert meta["ball_radius_mm"] == 2.0 and meta["mm_per_px"] == 0.0295
    assert (meta["image_height_px"], meta["image_width_px"]) == (480, 640)
    # No colour change is flat, everywhere on the pad.
    flat = calibration.levels**3 // 2
    index = np.arange(calibration.tile_count) * calibration.levels**3 + flat
    assert np.abs(calibration.table_gx[index]).max() < 0.02
    assert np.abs(calibration.table_gy[index]).max() < 0.02
    # The table reproduces the slopes it was fitted on: a strong lookup, not noise.
    assert np.abs(calibration.table_gx).max() > 1.0


def test_save_load_round_trip(small_calibration: GelSightLUT, tmp_path: Path) -> None:
    path = small_calibration.save(tmp_path / "sub" / "calib.npz")
    assert sorted(p.name for p in path.parent.iterdir()) == ["calib.npz"]  # no temp left
    loaded = GelSightLUT.load(path)
    np.testing.assert_array_equal(loaded.table_gx, small_calibration.table_gx)
    np.testing.assert_array_equal(loaded.table_gy, small_calibration.table_gy)
    assert dataclasses.replace(loaded, table_gx=None, table_gy=None) == dataclasses.replace(
        small_calibration, table_gx=None, table_gy=None
    )


def _write_npz(path: Path, **arrays: np.ndarray) -> Path:
    with path.open("wb") as file:
        np.savez(file, **arrays)
    return path


def test_corrupt_or_mismatched_files_are_named(
    small_calibration: GelSightLUT, tmp_path: Path
) -> None:
    with pytest.raises(FileNotFoundError, match="does not exist"):
        GelSightLUT.load(tmp_path / "missing.npz")

    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file at all")
    with pytest.raises(GelSightLUTError, match="corrupt"):
        GelSightLUT.load(garbage)

    good = small_calibration.save(tmp_path / "good.npz")
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(GelSightLUTError, match="corrupt"):
        GelSightLUT.load(truncated)

    tables = {"table_gx": small_calibration.table_gx, "table_gy": small_calibration.table_gy}
    no_meta = _write_npz(tmp_path / "no_meta.npz", **tables)
    with pytest.raises(GelSightLUTError, match="no metadata"):
        GelSightLUT.load(no_meta)

    meta = small_calibration.metadata()
    newer = _write_npz(
        tmp_path / "newer.npz",
        metadata=np.array(json.dumps({**meta, "version": FORMAT_VERSION + 1})),
        **tables,
    )
    with pytest.raises(GelSightLUTError, match="format version 2"):
        GelSightLUT.load(newer)

    resized = _write_npz(
        tmp_path / "resized.npz",
        metadata=np.array(json.dumps({**meta, "image_width_px": 320})),
        **tables,
    )
    with pytest.raises(GelSightLUTError, match="table_gx has shape"):
        GelSightLUT.load(resized)

    other = _write_npz(tmp_path / "other.npz", metadata=np.array(json.dumps({"a": 1})), **tables)
    with pytest.raises(GelSightLUTError, match="not a touchshape-gelsight-calibration"):
        GelSightLUT.load(other)

    nan = small_calibration.table_gx.copy()
    nan[3] = np.nan
    with pytest.raises(GelSightLUTError, match="non-finite"):
        dataclasses.replace(small_calibration, table_gx=nan).validate()


def test_folder_calibration_equals_datapack_calibration(
    pack: DataPack, small_calibration: GelSightLUT, tmp_path: Path
) -> None:
    # The same presses as PNG files (RGB on disk) + CSV give the same table: channel order,
    # centre (x = column) and radius columns all go through.
    lines = ["image,center_x_px,center_y_px,radius_px"]
    for index in FEW_FRAMES:
        save_png(tmp_path / f"press_{index}.png", pack.images_bgr[index])
        x, y = pack.centres_px[index]
        lines.append(f"press_{index}.png,{x},{y},{pack.radii_px[index]}")
    (tmp_path / "presses.csv").write_text("\n".join(lines) + "\n")
    reference = save_png(tmp_path / "reference.png", pack.reference_bgr)
    np.testing.assert_array_equal(read_image_bgr(reference), pack.reference_bgr)

    presses = load_press_folder(tmp_path, tmp_path / "presses.csv")
    assert [p.name for p in presses] == [f"press_{i}.png" for i in FEW_FRAMES]
    calibration = build_lut(
        presses, read_image_bgr(reference), ball_radius_mm=2.0, mm_per_px=0.0295
    )
    np.testing.assert_array_equal(calibration.table_gx, small_calibration.table_gx)
    np.testing.assert_array_equal(calibration.table_gy, small_calibration.table_gy)


def test_folder_input_errors(pack: DataPack, tmp_path: Path) -> None:
    csv_path = tmp_path / "presses.csv"
    csv_path.write_text("image,center_x_px,center_y_px,radius_px\n")
    with pytest.raises(GelSightLUTError, match="frame list is empty"):
        load_press_folder(tmp_path, csv_path)
    csv_path.write_text("image,x,y,radius_px\na.png,1,2,3\n")
    with pytest.raises(GelSightLUTError, match=r"lacks column\(s\) \['center_x_px'"):
        load_press_folder(tmp_path, csv_path)
    csv_path.write_text("image,center_x_px,center_y_px,radius_px\na.png,1,two,3\n")
    with pytest.raises(GelSightLUTError, match="line 2: not a number"):
        load_press_folder(tmp_path, csv_path)
    csv_path.write_text("image,center_x_px,center_y_px,radius_px\nmissing.png,1,2,3\n")
    with pytest.raises(FileNotFoundError, match=r"missing\.png"):
        load_press_folder(tmp_path, csv_path)

    grey = tmp_path / "grey.png"
    Image.fromarray(pack.reference_bgr[:, :, 0]).save(grey)
    with pytest.raises(GelSightLUTError, match=r"1 channel\(s\)"):
        read_image_bgr(grey)
    press = dataclasses.replace(pack.press(0), radius_px=80.0)
    with pytest.raises(GelSightLUTError, match=r"contact radius 80\.0 px"):
        build_lut([press], pack.reference_bgr, ball_radius_mm=2.0, mm_per_px=0.0295)
    small = dataclasses.replace(pack.press(0), image_bgr=pack.images_bgr[0, :240, :320])
    with pytest.raises(GelSightLUTError, match="320x240 px, the calibration is for 640x480"):
        build_lut([small], pack.reference_bgr, ball_radius_mm=2.0, mm_per_px=0.0295)
    with pytest.raises(GelSightLUTError, match="empty"):
        build_lut([], pack.reference_bgr, ball_radius_mm=2.0, mm_per_px=0.0295)


def test_check_image_names_the_problem() -> None:
    check_image(np.zeros((4, 5, 3), np.uint8), "frame", (4, 5))
    with pytest.raises(GelSightLUTError, match=r"frame has 1 channel\(s\)"):
        check_image(np.zeros((4, 5), np.uint8), "frame")
    with pytest.raises(GelSightLUTError, match=r"has 4 channel\(s\)"):
        check_image(np.zeros((4, 5, 4), np.uint8), "frame")
    with pytest.raises(GelSightLUTError, match="float32: GelSight frames are 8-bit"):
        check_image(np.zeros((4, 5, 3), np.float32), "frame")
    with pytest.raises(GelSightLUTError, match="5x4 px, the calibration is for 6x4"):
        check_image(np.zeros((4, 5, 3), np.uint8), "frame", (4, 6))
