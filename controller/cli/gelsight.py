"""`touchshape gelsight calibrate|reconstruct|evaluate`: the GelSight lookup table, height maps
and their accuracy.

Every input is read and checked before anything is written, and outputs appear whole or not at
all (models.files).
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from models.files import write_folder_atomically, write_json_atomically
from models.tactile.evaluation import (
    PressAccuracy,
    evaluate_press,
    forward_model_depth_mm,
    forward_model_simulator,
    run_sim_closed_loop,
    sim_table,
    summarise,
)
from models.tactile.lut import (
    DATAPACK_BALL_RADIUS_MM,
    DATAPACK_MM_PER_PX,
    GelSightLUT,
    GelSightLUTError,
    ImageBGR,
    build_lut,
    build_lut_from_datapack,
    check_image,
    default_datapack_path,
    load_datapack,
    load_press_folder,
    parse_frames,
    read_image_bgr,
)
from models.tactile.reconstruction import (
    TactileReconstruction,
    TactileReconstructor,
    contact_geometry,
)

CALIBRATE_EPILOG = """examples:
  touchshape gelsight calibrate --frames even --out logs/gelsight/calib.npz
  touchshape gelsight calibrate --datapack pack.npz --frames 0,2,4 --ball-radius-mm 2.0 \\
      --mm-per-px 0.0295 --out calib.npz
  touchshape gelsight calibrate --images presses/ --csv presses.csv --reference presses/ref.png \\
      --ball-radius-mm 2.0 --mm-per-px 0.0295 --out calib.npz

The CSV has a header row: image,center_x_px,center_y_px,radius_px (centre = column, row of the
ball's contact circle, radius of that circle in pixels; image = file name in --images).
"""
RECONSTRUCT_EPILOG = """examples:
  touchshape gelsight reconstruct --calib calib.npz --frames 1,3,5 --out logs/gelsight/rec
  touchshape gelsight reconstruct --calib calib.npz --image touch.png --reference ref.png --out rec

Writes <frame>.npy (indentation height map, mm, float32, HxW), <frame>.png (preview) and
summary.json (peak, contact size, centroid and mean normal in the pad frame) per frame.
"""
EVALUATE_EPILOG = """examples:
  touchshape gelsight evaluate                      # calibrate on even frames, score odd ones
  touchshape gelsight evaluate --calib calib.npz --test-frames odd --json report.json
  touchshape gelsight evaluate --fit-depth          # + absolute depth vs the simulator's
  touchshape gelsight evaluate --sim                # closed loop through the simulated sensor
"""


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add `gelsight calibrate|reconstruct|evaluate`."""
    gelsight = groups.add_parser("gelsight", help="GelSight calibration and height maps")
    commands = gelsight.add_subparsers(dest="command", required=True)
    raw = argparse.RawDescriptionHelpFormatter
    pack_help = "dataPack .npz of ball presses (default, or bare flag: taxim's real presses)"

    calibrate_parser = commands.add_parser(
        "calibrate",
        help="build the lookup table from ball presses",
        epilog=CALIBRATE_EPILOG,
        formatter_class=raw,
    )
    calibrate_parser.add_argument("--datapack", type=Path, nargs="?", const=None, help=pack_help)
    calibrate_parser.add_argument(
        "--frames", default="all", help="dataPack frames: all, even, odd or 0,2,4 (default all)"
    )
    calibrate_parser.add_argument("--images", type=Path, help="folder of your press images")
    calibrate_parser.add_argument("--csv", type=Path, help="centre and radius per image")
    calibrate_parser.add_argument("--reference", type=Path, help="no-contact image (--images)")
    calibrate_parser.add_argument(
        "--ball-radius-mm", type=float, help="ball radius, mm (dataPack default 2.0)"
    )
    calibrate_parser.add_argument(
        "--mm-per-px", type=float, help="pixel pitch on the gel, mm (dataPack default 0.0295)"
    )
    calibrate_parser.add_argument("--out", type=Path, required=True, help="calibration .npz")
    calibrate_parser.set_defaults(handler=_calibrate)

    reconstruct_parser = commands.add_parser(
        "reconstruct",
        help="height maps (mm) and contact masks from tactile images",
        epilog=RECONSTRUCT_EPILOG,
        formatter_class=raw,
    )
    reconstruct_parser.add_argument("--calib", type=Path, required=True, help="calibration .npz")
    reconstruct_parser.add_argument("--datapack", type=Path, nargs="?", const=None, help=pack_help)
    reconstruct_parser.add_argument(
        "--frames", default="all", help="dataPack frames: all, even, odd or 1,3,5 (default all)"
    )
    reconstruct_parser.add_argument(
        "--image", type=Path, action="append", default=[], help="tactile image (repeatable)"
    )
    reconstruct_parser.add_argument("--reference", type=Path, help="no-contact image (--image)")
    reconstruct_parser.add_argument("--out", type=Path, required=True, help="output folder")
    reconstruct_parser.set_defaults(handler=_reconstruct)

    evaluate_parser = commands.add_parser(
        "evaluate",
        help="accuracy table on held-out real presses (or the simulated sensor with --sim)",
        epilog=EVALUATE_EPILOG,
        formatter_class=raw,
    )
    evaluate_parser.add_argument("--datapack", type=Path, nargs="?", const=None, help=pack_help)
    evaluate_parser.add_argument("--calib-frames", default="even", help="default even")
    evaluate_parser.add_argument("--test-frames", default="odd", help="default odd")
    evaluate_parser.add_argument("--calib", type=Path, help="use this calibration instead")
    evaluate_parser.add_argument("--sim", action="store_true", help="simulated closed loop")
    evaluate_parser.add_argument(
        "--fit-depth",
        action="store_true",
        help="also estimate each press's depth with the simulator (absolute-depth cross-check)",
    )
    evaluate_parser.add_argument("--json", type=Path, help="also write the report as JSON")
    evaluate_parser.set_defaults(handler=_evaluate)


def _calibrate(args: argparse.Namespace) -> int:
    lut = run_calibrate(
        out=args.out,
        datapack=args.datapack,
        frames=args.frames,
        images=args.images,
        presses_csv=args.csv,
        reference=args.reference,
        ball_radius_mm=args.ball_radius_mm,
        mm_per_px=args.mm_per_px,
    )
    print(f"{args.out}: {len(lut.frames)} presses, {lut.tile_count} tiles")
    return 0


def _reconstruct(args: argparse.Namespace) -> int:
    paths = run_reconstruct(
        calib=args.calib,
        out=args.out,
        datapack=args.datapack,
        frames=args.frames,
        images=args.image,
        reference=args.reference,
    )
    for path in paths:
        print(path)
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    if args.sim:
        if args.calib is not None:
            lut = GelSightLUT.load(args.calib)
        else:
            pack = load_datapack(args.datapack or default_datapack_path())
            frames = parse_frames(args.calib_frames, len(pack.images_bgr))
            lut = build_lut_from_datapack(pack, frames)
        rows = run_sim_closed_loop(lut)
        report: dict[str, Any] = {"sim_closed_loop": rows}
        print(sim_table(rows), end="")
    else:
        report = run_evaluate(
            datapack=args.datapack,
            calib_frames=args.calib_frames,
            test_frames=args.test_frames,
            calib=args.calib,
            fit_depth=args.fit_depth,
        )
        print(accuracy_table(report), end="")
    if args.json is not None:
        write_json_atomically(args.json, report)
    return 0


def run_calibrate(
    *,
    out: Path,
    datapack: Path | None = None,
    frames: str = "all",
    images: Path | None = None,
    presses_csv: Path | None = None,
    reference: Path | None = None,
    ball_radius_mm: float | None = None,
    mm_per_px: float | None = None,
) -> GelSightLUT:
    """Calibrate from a dataPack's frames, or from a folder of images + CSV + reference image,
    and save the lookup table to ``out``.

    The dataPack defaults to taxim's real presses, whose ball radius (2.0 mm) and pixel pitch
    (0.0295 mm) are the defaults there; a folder of one's own presses must give both.
    """
    if images is not None or presses_csv is not None:
        if datapack is not None:
            raise GelSightLUTError("give either --datapack or --images/--csv, not both")
        lut = _calibrate_folder(images, presses_csv, reference, ball_radius_mm, mm_per_px)
    else:
        if reference is not None:
            raise GelSightLUTError("--reference is for --images: a dataPack has its own f0")
        pack_path = datapack or default_datapack_path()
        pack = load_datapack(pack_path)
        lut = build_lut_from_datapack(
            pack,
            parse_frames(frames, len(pack.images_bgr)),
            ball_radius_mm=DATAPACK_BALL_RADIUS_MM if ball_radius_mm is None else ball_radius_mm,
            mm_per_px=DATAPACK_MM_PER_PX if mm_per_px is None else mm_per_px,
            source=str(pack_path),
        )
    lut.save(out)
    return lut


def _calibrate_folder(
    images: Path | None,
    presses_csv: Path | None,
    reference: Path | None,
    ball_radius_mm: float | None,
    mm_per_px: float | None,
) -> GelSightLUT:
    """The lookup table from one's own presses: every one of the five inputs is required."""
    if (
        images is None
        or presses_csv is None
        or reference is None
        or ball_radius_mm is None
        or mm_per_px is None
    ):
        given = {
            "--images": images,
            "--csv": presses_csv,
            "--reference": reference,
            "--ball-radius-mm": ball_radius_mm,
            "--mm-per-px": mm_per_px,
        }
        missing = [flag for flag, value in given.items() if value is None]
        raise GelSightLUTError(f"calibrating from an image folder also needs {missing}")
    presses = load_press_folder(images, presses_csv)
    return build_lut(
        presses,
        read_image_bgr(reference),
        ball_radius_mm=ball_radius_mm,
        mm_per_px=mm_per_px,
        source=f"{images} ({presses_csv.name})",
    )


def _frames_to_reconstruct(
    datapack: Path | None,
    frames: str,
    images: list[Path],
    reference: Path | None,
    shape: tuple[int, int],
) -> tuple[ImageBGR, list[tuple[str, ImageBGR]]]:
    """Reference frame and (name, image) pairs from a dataPack or from image files, each
    checked against the lookup table's image ``shape`` (the error names the file)."""
    if images:
        if datapack is not None:
            raise GelSightLUTError("give either --datapack or --image, not both")
        if reference is None:
            raise GelSightLUTError(
                "missing reference image: --image needs --reference, the same sensor's"
                " no-contact frame"
            )
        names = [path.stem for path in images]
        if len(set(names)) != len(names):
            raise GelSightLUTError(f"image names {names} repeat: outputs would overwrite")
        loaded = [(path, read_image_bgr(path)) for path in [reference, *images]]
        for path, image in loaded:
            check_image(image, f"image {path}", shape)
        return loaded[0][1], [(path.stem, image) for path, image in loaded[1:]]
    if reference is not None:
        raise GelSightLUTError("--reference is for --image: a dataPack has its own f0")
    pack_path = datapack or default_datapack_path()
    pack = load_datapack(pack_path)
    check_image(pack.reference_bgr, f"dataPack {pack_path} reference image", shape)
    indices = parse_frames(frames, len(pack.images_bgr))
    return pack.reference_bgr, [(str(i), pack.images_bgr[i]) for i in indices]


def run_reconstruct(
    *,
    calib: Path,
    out: Path,
    datapack: Path | None = None,
    frames: str = "all",
    images: list[Path] | None = None,
    reference: Path | None = None,
) -> list[Path]:
    """Write ``<frame>.npy`` (height, mm float32), ``<frame>.png`` previews and summary.json."""
    lut = GelSightLUT.load(calib)
    reference_bgr, named_images = _frames_to_reconstruct(
        datapack, frames, images or [], reference, lut.image_shape
    )
    reconstructor = TactileReconstructor(lut, reference_bgr)
    results = [(name, image, reconstructor.reconstruct(image)) for name, image in named_images]

    summary: dict[str, Any] = {"calibration": str(calib), "frames": {}}
    writers: dict[str, Callable[[Path], None]] = {}
    for name, image, result in results:
        contact = contact_geometry(result.height_mm, result.contact_mask, result.mm_per_px)
        summary["frames"][name] = {
            "peak_mm": round(result.peak_mm, 4),
            "contact_px": int(np.count_nonzero(result.contact_mask)),
            "centroid_pad_mm": None
            if contact is None
            else contact.centroid_pad_mm.round(4).tolist(),
            "normal_pad": None if contact is None else contact.normal_pad.round(4).tolist(),
        }
        writers[f"{name}.npy"] = lambda path, h=result.height_mm: np.save(path, h)
        writers[f"{name}.png"] = lambda path, n=name, i=image, r=result: save_preview(path, n, i, r)
    writers["summary.json"] = lambda path: path.write_text(json.dumps(summary, indent=2) + "\n")
    return write_folder_atomically(out, writers)


def save_preview(path: Path, name: str, image_bgr: ImageBGR, result: TactileReconstruction) -> None:
    """PNG: the raw frame beside the height map (mm colour scale) with the contact outlined."""
    # Imported here: matplotlib adds ~0.3 s to every CLI start and only previews need it.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(10, 3.8), dpi=80, layout="constrained")
    FigureCanvasAgg(figure)
    raw_axes, height_axes = figure.subplots(1, 2)
    raw_axes.imshow(image_bgr[:, :, ::-1])
    raw_axes.set_title(f"frame {name} (raw)")
    shown = height_axes.imshow(result.height_mm, cmap="viridis")
    if result.contact_mask.any():
        height_axes.contour(result.contact_mask, levels=[0.5], colors="white", linewidths=0.8)
    height_axes.set_title(f"indentation, peak {result.peak_mm:.2f} mm (white: contact)")
    figure.colorbar(shown, ax=height_axes, label="mm")
    for axes in (raw_axes, height_axes):
        axes.set_xticks([])
        axes.set_yticks([])
    figure.savefig(path)


def run_evaluate(
    *,
    datapack: Path | None = None,
    calib_frames: str = "even",
    test_frames: str = "odd",
    calib: Path | None = None,
    fit_depth: bool = False,
) -> dict[str, Any]:
    """Calibrate on some dataPack frames (or load ``calib``), reconstruct others, score them.

    Returns the per-frame :class:`PressAccuracy` rows and :func:`summarise`'s medians. With
    ``fit_depth`` each row also gets the simulator-matched press depth
    (:func:`forward_model_depth_mm`) and the raw peak's error against it (~0.5 s a frame).
    """
    pack_path = datapack or default_datapack_path()
    pack = load_datapack(pack_path)
    count = len(pack.images_bgr)
    test = parse_frames(test_frames, count)
    if calib is not None:
        lut = GelSightLUT.load(calib)
    else:
        train = parse_frames(calib_frames, count)
        overlap = sorted(set(train) & set(test))
        if overlap:
            raise GelSightLUTError(f"frames {overlap} are both calibration and test frames")
        lut = build_lut_from_datapack(pack, train, source=str(pack_path))
    reconstructor = TactileReconstructor(lut, pack.reference_bgr)
    rows: list[PressAccuracy] = []
    for index in test:
        result = reconstructor.reconstruct(pack.images_bgr[index])
        rows.append(
            evaluate_press(
                result.height_mm,
                result.contact_mask,
                pack.press(index),
                ball_radius_mm=lut.ball_radius_mm,
                mm_per_px=lut.mm_per_px,
            )
        )
    report = {
        "datapack": str(pack_path),
        "calibration_frames": list(lut.frames),
        "test_frames": [str(i) for i in test],
        "summary": summarise(rows, lut.ball_radius_mm),
        "frames": [asdict(row) for row in rows],
    }
    if fit_depth:
        simulator = forward_model_simulator(lut.mm_per_px, lut.image_shape)
        for index, row in zip(test, report["frames"], strict=True):
            depth = forward_model_depth_mm(simulator, pack.press(index), lut.ball_radius_mm)
            peak = row["cap_depth_mm"] * (1.0 + row["peak_error_absolute"])
            row["model_depth_mm"] = depth
            row["peak_error_model"] = peak / depth - 1.0
        report["summary"]["median_abs_peak_error_model"] = statistics.median(
            abs(row["peak_error_model"]) for row in report["frames"]
        )
    return report


def accuracy_table(report: dict[str, Any]) -> str:
    """Markdown table of :func:`run_evaluate`'s report: one row per frame, then the medians."""
    model = "median_abs_peak_error_model" in report["summary"]
    header = (
        "| frame | fitted radius (mm) | RMSE (mm) | peak error | peak error vs rim |"
        " raw peak error | contact IoU |"
        + (" model depth (mm) | raw peak vs model depth |" if model else "")
        + "\n|---|---|---|---|---|---|---|"
        + ("---|---|" if model else "")
        + "\n"
    )
    lines = [
        f"| {r['frame']} | {r['fitted_radius_mm']:.3f} | {r['rmse_mm']:.3f} |"
        f" {r['peak_error']:+.1%} | {r['peak_error_rim']:+.1%} |"
        f" {r['peak_error_absolute']:+.1%} | {r['contact_iou']:.2f} |"
        + (f" {r['model_depth_mm']:.3f} | {r['peak_error_model']:+.1%} |" if model else "")
        for r in report["frames"]
    ]
    s = report["summary"]
    lines.append(
        f"| **median** | **{s['median_fitted_radius_mm']:.3f}** | **{s['median_rmse_mm']:.3f}** |"
        f" **{s['median_abs_peak_error']:.1%}** (abs) | **{s['median_abs_peak_error_rim']:.1%}**"
        f" (abs) | **{s['median_abs_peak_error_absolute']:.1%}** (abs) |"
        f" **{s['median_contact_iou']:.2f}** |"
        + (f" | **{s['median_abs_peak_error_model']:.1%}** (abs) |" if model else "")
    )
    worst = s["worst_frame"]
    pedestal = statistics.median([r["offset_mm"] for r in report["frames"]])
    return (
        header
        + "\n".join(lines)
        + f"\n\nWorst frame (largest RMSE): {worst['frame']}, RMSE {worst['rmse_mm']:.3f} mm,"
        f" fitted radius {worst['fitted_radius_mm']:.3f} mm. Median pedestal (best offset)"
        f" {pedestal:.3f} mm.\n"
    )
