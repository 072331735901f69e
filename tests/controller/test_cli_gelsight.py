"""`touchshape gelsight ...` and `touchshape bench gelsight`: outputs, and every bad input ->
exit code 2 with the problem named and nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from controller.benchmarks.gelsight import benchmark_gelsight
from controller.cli.main import main
from models.tactile.lut import (
    DataPack,
    GelSightLUT,
    build_lut,
    default_datapack_path,
    load_datapack,
)

CALIB_FRAMES = "0,2,4,6"


@pytest.fixture(scope="module")
def pack() -> DataPack:
    return load_datapack(default_datapack_path())


@pytest.fixture(scope="module")
def calib_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("calib") / "calib.npz"
    assert main(["gelsight", "calibrate", "--frames", CALIB_FRAMES, "--out", str(path)]) == 0
    return path


def save_png(path: Path, image_bgr: np.ndarray) -> Path:
    Image.fromarray(np.ascontiguousarray(image_bgr[..., ::-1])).save(path)
    return path


def listing(folder: Path) -> list[str]:
    """Every entry under ``folder``, hidden temporaries included."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def test_calibrate_writes_a_versioned_file(calib_file: Path) -> None:
    calibration = GelSightLUT.load(calib_file)
    assert calibration.frames == ("0", "2", "4", "6")
    assert calibration.ball_radius_mm == 2.0 and calibration.mm_per_px == 0.0295
    assert listing(calib_file.parent) == ["calib.npz"]


def test_reconstruct_datapack_frames(calib_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "rec"
    argv = ["gelsight", "reconstruct", "--calib", str(calib_file), "--frames", "1,3"]
    assert main([*argv, "--out", str(out)]) == 0
    assert listing(tmp_path) == [
        "rec",
        "rec/1.npy",
        "rec/1.png",
        "rec/3.npy",
        "rec/3.png",
        "rec/summary.json",
    ]
    height = np.load(out / "1.npy")
    assert height.dtype == np.float32 and height.shape == (480, 640)
    assert height.min() >= 0.0 and 1.0 < height.max() < 2.5
    summary = json.loads((out / "summary.json").read_text())
    frame = summary["frames"]["1"]
    assert frame["contact_px"] > 5000
    assert frame["normal_pad"][2] < -0.99  # pressed square on: the ball's normal is -z
    # Pixel (row 169, col 300) of frame 1's annotated centre, in the pad frame (mm).
    expected_xy = [(300 - 319.5) * 0.0295, (169 - 239.5) * 0.0295]
    np.testing.assert_allclose(frame["centroid_pad_mm"][:2], expected_xy, atol=0.1)
    with Image.open(out / "1.png") as preview:
        assert preview.size[0] > 400

    # Into an existing folder: files are replaced, nothing else is left behind.
    assert main([*argv[:-1], "5", "--out", str(out)]) == 0
    assert "rec/5.npy" in listing(tmp_path) and len(listing(tmp_path)) == 8


def test_reconstruct_image_files(pack: DataPack, calib_file: Path, tmp_path: Path) -> None:
    touch = save_png(tmp_path / "touch.png", pack.images_bgr[7])
    reference = save_png(tmp_path / "reference.png", pack.reference_bgr)
    out = tmp_path / "rec"
    argv = ["gelsight", "reconstruct", "--calib", str(calib_file), "--image", str(touch)]
    assert main([*argv, "--reference", str(reference), "--out", str(out)]) == 0
    from_png = np.load(out / "touch.npy")
    assert main(["gelsight", "reconstruct", "--calib", str(calib_file), "--frames", "7", "--out",
                 str(tmp_path / "pack")]) == 0  # fmt: skip
    np.testing.assert_array_equal(from_png, np.load(tmp_path / "pack" / "7.npy"))


def _expect_error(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 2
    assert message in capsys.readouterr().err


@pytest.fixture
def small_calib(pack: DataPack, tmp_path: Path) -> Path:
    """A valid calibration for 320x240 frames (a crop of the real presses)."""
    crop = pack.images_bgr[:4, :240, :320]
    from models.tactile.lut import BallPress

    presses = [BallPress(crop[i], (150.0, 120.0), 40.0, str(i)) for i in range(4)]
    calibration = build_lut(
        presses, pack.reference_bgr[:240, :320], ball_radius_mm=2.0, mm_per_px=0.0295
    )
    return calibration.save(tmp_path / "small.npz")


def test_bad_inputs_exit_2_and_write_nothing(
    pack: DataPack,
    calib_file: Path,
    small_calib: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    work = tmp_path / "work"
    work.mkdir()
    out = work / "out"
    reference = save_png(work / "reference.png", pack.reference_bgr)
    grey = work / "grey.png"
    Image.fromarray(pack.images_bgr[1, :, :, 1]).save(grey)
    small = save_png(work / "small.png", pack.images_bgr[1, :240, :320])
    corrupt = work / "corrupt.npz"
    corrupt.write_bytes(b"PK\x03\x04 this is not really a zip")
    before = listing(work)

    rec = ["gelsight", "reconstruct", "--out", str(out), "--calib"]
    cases = [
        ([*rec, str(calib_file), "--image", str(small), "--reference", str(reference)],
         "image /...small.png is 320x240 px, the calibration is for 640x480"),
        ([*rec, str(calib_file), "--image", str(grey), "--reference", str(reference)],
         "grey.png has 1 channel(s)"),
        ([*rec, str(calib_file), "--image", str(small)], "missing reference image"),
        ([*rec, str(calib_file), "--image", str(small), "--reference", str(work / "nope.png")],
         "nope.png does not exist"),
        ([*rec, str(corrupt), "--frames", "1"], "corrupt or not a touchshape GelSight"),
        ([*rec, str(work / "none.npz"), "--frames", "1"], "none.npz does not exist"),
        ([*rec, str(small_calib), "--frames", "1"],
         "reference image is 640x480 px, the calibration is for 320x240"),
        ([*rec, str(calib_file), "--frames", ""], "frame list '' is empty"),
        ([*rec, str(calib_file), "--frames", "99"], "[99] out of range"),
        (["gelsight", "calibrate", "--frames", "", "--out", str(out)], "is empty"),
        (["gelsight", "calibrate", "--frames", "0", "--out", str(work)], "is a folder"),
        (["gelsight", "calibrate", "--images", str(work), "--out", str(out)],
         "also needs ['--csv', '--reference', '--ball-radius-mm', '--mm-per-px']"),
        (["gelsight", "evaluate", "--calib-frames", "0,1", "--test-frames", "1,3"],
         "frames [1] are both calibration and test frames"),
    ]  # fmt: skip
    for argv, message in cases:
        # Messages naming a file in tmp_path: match the text around its path.
        head, _, tail = message.partition("...")
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert head in err and tail in err, (argv, err)
        assert listing(work) == before, argv


def test_folder_calibration_via_cli(
    pack: DataPack, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "presses"
    folder.mkdir()
    rows = ["image,center_x_px,center_y_px,radius_px"]
    for index in (0, 2):
        save_png(folder / f"{index}.png", pack.images_bgr[index])
        x, y = pack.centres_px[index]
        rows.append(f"{index}.png,{x},{y},{pack.radii_px[index]}")
    csv_path = tmp_path / "presses.csv"
    csv_path.write_text("\n".join(rows) + "\n")
    reference = save_png(tmp_path / "reference.png", pack.reference_bgr)
    out = tmp_path / "calib.npz"
    argv = ["gelsight", "calibrate", "--images", str(folder), "--csv", str(csv_path)]
    argv += ["--reference", str(reference), "--mm-per-px", "0.0295", "--out", str(out)]
    assert main([*argv, "--ball-radius-mm", "2.0"]) == 0
    assert GelSightLUT.load(out).frames == ("0.png", "2.png")

    csv_path.write_text("image,center_x_px,center_y_px,radius_px\n")
    out.unlink()
    _expect_error([*argv, "--ball-radius-mm", "2.0"], "frame list is empty", capsys)
    assert not out.exists()


def test_evaluate_prints_the_accuracy_table(
    calib_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report = tmp_path / "report.json"
    argv = ["gelsight", "evaluate", "--calib", str(calib_file), "--test-frames", "1,3"]
    assert main([*argv, "--json", str(report)]) == 0
    table = capsys.readouterr().out
    assert table.startswith("| frame | fitted radius (mm) | RMSE (mm) |")
    assert "| **median** |" in table and "Worst frame" in table
    data = json.loads(report.read_text())
    assert data["test_frames"] == ["1", "3"] and len(data["frames"]) == 2


def test_bench_reports_the_keys_and_an_honest_baseline() -> None:
    result = benchmark_gelsight(frames=3)
    assert {"fps", "fps_straightforward", "peak_memory_mb"} <= result.keys()
    assert result["frames"] == 3 and result["resolution"] == [640, 480]
    # The rates are the inverse of the median frame times, and the speed-up is their ratio.
    assert result["fps"] == pytest.approx(1e3 / result["median_ms"], rel=0.01, abs=0.1)
    straightforward_fps = 1e3 / result["median_ms_straightforward"]
    assert result["fps_straightforward"] == pytest.approx(straightforward_fps, rel=0.01, abs=0.1)
    ratio = result["median_ms_straightforward"] / result["median_ms"]
    assert result["speedup"] == pytest.approx(ratio, rel=0.01, abs=0.01)
    # The peak holds at least the frame's height map (640 x 480 float64: 2.3 MB).
    assert result["peak_memory_mb"] >= 640 * 480 * 8 / 2**20
    # The baseline computes the same height maps (the textbook DST-I's zero border and
    # half-pixel-shifted differences account for the rest; measured 0.053 mm).
    assert result["max_height_difference_mm"] < 0.1
