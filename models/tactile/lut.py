"""The GelSight lookup table (LUT): image colour -> surface gradients, position-aware.

The paper inverts the sensor's reflectance with a table built from presses of a ball of known
radius (the sensor's calibration): inside each press the surface gradients are known
analytically, so every pixel gives one (colour change, gradient) sample. This module reads the
presses, builds that table and stores it, with two changes that the real data asks for (see
docs/gelsight.md):

- **Position-aware.** Illumination varies across the pad (the same slope changes the colour
  more in one place than in another), so the pad is cut into square tiles and every tile has
  its own table, built from the samples near it (Gaussian weights over the sample's pixel
  position) and shrunk toward the whole-pad table where it has few samples.
- **No false "flat" labels.** The gel sinks in a skirt around the annotated contact circle;
  labelling those pixels flat teaches the table that sloped colours mean zero slope. Pixels
  between 1 and 2 contact radii are left out, and flat pixels (beyond) are down-weighted so
  that their sheer number does not shrink small slopes toward zero.

Conventions: images are HxWx3 uint8 BGR (as the camera gives them), the colour change is
image - reference per channel. Gradients are of the indentation h (>= 0 into the gel) over the
pad's x (image columns) and y (image rows), dimensionless (mm/mm = px/px). ``centre_px`` is
(x, y) = (column, row), radii are in pixels.
"""

from __future__ import annotations

import csv
import json
import math
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse
from numpy.typing import NDArray
from PIL import Image

from models.files import write_atomically

ImageBGR = NDArray[np.uint8]

# The file format of a saved table, named after the calibration that produces it.
FORMAT_NAME = "touchshape-gelsight-calibration"
FORMAT_VERSION = 1

# The real presses of taxim's dataPack: a 2.0 mm ball imaged at 0.0295 mm per pixel.
DATAPACK_BALL_RADIUS_MM = 2.0
DATAPACK_MM_PER_PX = 0.0295

# Colour changes are binned per channel in steps of COLOUR_STEP grey levels centred on 0 and
# clipped at +-COLOUR_LIMIT: finer steps or a wider range did not improve held-out presses.
COLOUR_STEP = 8
COLOUR_LIMIT = 64
# Tile edge, which is also the width of the Gaussian sample weights. Smaller tiles or narrower
# weights leave too few presses per tile.
TILE_PX = 80
# Samples are pooled in cells of this size before the per-tile weighting; a cell is small
# against the weight width, so pooling barely changes the weights.
_CELL_PX = 16
# A tile's table is (tile samples + PRIOR_COUNT x whole-pad mean) / (tile weight + PRIOR_COUNT):
# where a tile saw a colour only a few times it leans on the whole pad.
PRIOR_COUNT = 5.0
# Pixels between 1 and SKIRT_FACTOR contact radii are not labelled: the gel there sinks by an
# unknown amount (the skirt around the ball). Labelling them flat makes the table read small
# slopes as flat, so larger, flatter objects come out too shallow.
SKIRT_FACTOR = 2.0
# Weight of a flat pixel (beyond the skirt) against a contact pixel's 1: flat pixels far
# outnumber contact pixels, and at full weight they pull the table's small slopes toward zero.
FLAT_WEIGHT = 0.1


class GelSightLUTError(ValueError):
    """A lookup-table file or its input (presses, frames, images) is unusable; the message names
    the problem."""


@dataclass(frozen=True)
class BallPress:
    """One calibration press: a ball pressed into the pad, its contact circle annotated."""

    image_bgr: ImageBGR
    centre_px: tuple[float, float]
    radius_px: float
    name: str


@dataclass(frozen=True)
class DataPack:
    """Ball presses in taxim's dataPack layout: the no-contact frame and the pressed frames."""

    reference_bgr: ImageBGR
    images_bgr: NDArray[np.uint8]
    centres_px: NDArray[np.float64]
    radii_px: NDArray[np.float64]
    names: tuple[str, ...]

    def press(self, index: int) -> BallPress:
        """Frame ``index`` as a :class:`BallPress`."""
        centre = (float(self.centres_px[index, 0]), float(self.centres_px[index, 1]))
        return BallPress(self.images_bgr[index], centre, float(self.radii_px[index]), str(index))


def default_datapack_path() -> Path:
    """The real GelSight presses shipped inside the installed ``taxim`` package."""
    return Path(str(files("taxim") / "calib" / "gelsight" / "dataPack.npz"))


def load_datapack(path: Path | str) -> DataPack:
    """Read a dataPack .npz (``f0``, ``imgs``, ``touch_center``, ``touch_radius``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"dataPack {path} does not exist")
    try:
        with np.load(path) as pack:
            missing = {"f0", "imgs", "touch_center", "touch_radius"} - set(pack.files)
            if missing:
                raise GelSightLUTError(f"dataPack {path} lacks {sorted(missing)}")
            reference = np.asarray(pack["f0"])
            images = np.asarray(pack["imgs"])
            centres = np.asarray(pack["touch_center"], dtype=np.float64)
            radii = np.asarray(pack["touch_radius"], dtype=np.float64)
            names = tuple(str(n) for n in pack["names"]) if "names" in pack.files else ()
    except (zipfile.BadZipFile, OSError, EOFError) as error:
        raise GelSightLUTError(f"dataPack {path} is not a readable .npz file: {error}") from None
    check_image(reference, "dataPack reference f0")
    if images.ndim != 4 or images.shape[1:] != reference.shape or images.dtype != np.uint8:
        raise GelSightLUTError(
            f"dataPack {path}: imgs {images.shape} {images.dtype} do not match f0 {reference.shape}"
        )
    if centres.shape != (len(images), 2) or radii.shape != (len(images),):
        raise GelSightLUTError(
            f"dataPack {path}: {len(images)} images but touch_center {centres.shape},"
            f" touch_radius {radii.shape}"
        )
    return DataPack(reference, images, centres, radii, names or tuple(map(str, range(len(images)))))


def parse_frames(spec: str, count: int) -> list[int]:
    """Frame indices from ``all``, ``even``, ``odd`` or a comma list such as ``1,3,5``."""
    spec = spec.strip()
    named = {"all": range(count), "even": range(0, count, 2), "odd": range(1, count, 2)}
    if spec in named:
        frames = list(named[spec])
    else:
        try:
            frames = [int(part) for part in spec.split(",") if part.strip()]
        except ValueError:
            raise GelSightLUTError(
                f"frames {spec!r}: give all, even, odd or comma-separated indices"
            ) from None
        outside = [f for f in frames if not 0 <= f < count]
        if outside:
            raise GelSightLUTError(f"frames {outside} out of range: the dataPack has {count}")
    if not frames:
        raise GelSightLUTError(f"frame list {spec!r} is empty")
    return frames


def check_image(image: NDArray[Any], what: str, shape: tuple[int, int] | None = None) -> None:
    """Raise a GelSightLUTError naming ``what`` unless it is an HxWx3 uint8 image (of ``shape``)."""
    if image.ndim != 3 or image.shape[2] != 3:
        channels = 1 if image.ndim == 2 else (image.shape[2] if image.ndim == 3 else "?")
        raise GelSightLUTError(
            f"{what} has {channels} channel(s), shape {image.shape}: GelSight frames are"
            " 3-channel colour (HxWx3)"
        )
    if image.dtype != np.uint8:
        raise GelSightLUTError(f"{what} is {image.dtype}: GelSight frames are 8-bit (uint8)")
    if shape is not None and image.shape[:2] != tuple(shape):
        raise GelSightLUTError(
            f"{what} is {image.shape[1]}x{image.shape[0]} px, the calibration is for"
            f" {shape[1]}x{shape[0]}"
        )


def read_image_bgr(path: Path | str) -> ImageBGR:
    """Read a colour image file (PNG, JPEG, ...) as HxWx3 uint8 BGR.

    Image files store RGB (OpenCV's imwrite converts BGR on writing), so the channels are
    reversed to the camera's BGR order.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image {path} does not exist")
    try:
        with Image.open(path) as image:
            bands = image.getbands()
            if bands != ("R", "G", "B"):
                raise GelSightLUTError(
                    f"image {path} has {len(bands)} channel(s) ({image.mode}): GelSight frames"
                    " are 3-channel colour"
                )
            rgb = np.asarray(image.convert("RGB"))
    except (OSError, Image.DecompressionBombError) as error:
        raise GelSightLUTError(f"image {path} cannot be read: {error}") from None
    return np.ascontiguousarray(rgb[:, :, ::-1])


def load_press_folder(folder: Path | str, csv_path: Path | str) -> list[BallPress]:
    """Ball presses from a folder of images and a CSV ``image,center_x_px,center_y_px,radius_px``.

    ``image`` is a file name inside ``folder``; the centre is (column, row) in pixels.
    """
    folder, csv_path = Path(folder), Path(csv_path)
    if not folder.is_dir():
        raise FileNotFoundError(f"image folder {folder} does not exist")
    if not csv_path.is_file():
        raise FileNotFoundError(f"press CSV {csv_path} does not exist")
    columns = ("image", "center_x_px", "center_y_px", "radius_px")
    with csv_path.open(newline="") as file:
        reader = csv.DictReader(file)
        missing = [c for c in columns if c not in (reader.fieldnames or [])]
        if missing:
            raise GelSightLUTError(f"press CSV {csv_path} lacks column(s) {missing}")
        rows = list(reader)
    if not rows:
        raise GelSightLUTError(f"press CSV {csv_path} lists no images: the frame list is empty")
    presses = []
    for line, row in enumerate(rows, start=2):
        try:
            centre = (float(row["center_x_px"]), float(row["center_y_px"]))
            radius = float(row["radius_px"])
        except (TypeError, ValueError):
            raise GelSightLUTError(f"press CSV {csv_path} line {line}: not a number") from None
        image = read_image_bgr(folder / row["image"])
        presses.append(BallPress(image, centre, radius, row["image"]))
    return presses


def colour_level_luts(step: int, limit: int) -> tuple[NDArray[np.int32], int]:
    """Lookup from (colour change + 255) to its bin level, and the number of levels per channel.

    One 511-entry table per sensor replaces a float division, rounding and clipping per pixel;
    calibration and reconstruction both bin through it, so they cannot disagree.
    """
    half = limit // step
    change = np.arange(-255, 256)
    levels = np.clip(np.floor(change / step + 0.5), -half, half).astype(np.int32) + half
    return levels, 2 * half + 1


def tile_grid(shape: tuple[int, int], tile_px: int) -> tuple[NDArray[np.int32], int, int]:
    """Tile index of every pixel (HxW int32, row-major tiles) and the tile rows and columns."""
    rows = math.ceil(shape[0] / tile_px)
    cols = math.ceil(shape[1] / tile_px)
    r = np.arange(shape[0], dtype=np.int32)[:, None] // tile_px
    c = np.arange(shape[1], dtype=np.int32)[None, :] // tile_px
    return r * cols + c, rows, cols


@dataclass(frozen=True)
class GelSightLUT:
    """Position-aware lookup table (tile, colour) -> indentation gradients, with its metadata.

    ``table_gx`` / ``table_gy`` (float32) hold dh/dx and dh/dy (dimensionless, x = image
    columns, y = image rows) at index ``tile * levels**3 + colour``, where ``colour`` combines
    the B, G, R levels of image - reference (see :func:`colour_level_luts`).
    """

    table_gx: NDArray[np.float32]
    table_gy: NDArray[np.float32]
    image_shape: tuple[int, int]
    mm_per_px: float
    ball_radius_mm: float
    frames: tuple[str, ...]
    source: str
    colour_step: int = COLOUR_STEP
    colour_limit: int = COLOUR_LIMIT
    tile_px: int = TILE_PX

    @property
    def levels(self) -> int:
        """Colour levels per channel."""
        return colour_level_luts(self.colour_step, self.colour_limit)[1]

    @property
    def tile_count(self) -> int:
        """Number of tiles (tables) covering the image."""
        _, rows, cols = tile_grid(self.image_shape, self.tile_px)
        return rows * cols

    def metadata(self) -> dict[str, Any]:
        """Everything but the tables, as stored in the file (JSON types)."""
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "image_height_px": self.image_shape[0],
            "image_width_px": self.image_shape[1],
            "mm_per_px": self.mm_per_px,
            "ball_radius_mm": self.ball_radius_mm,
            "frames": list(self.frames),
            "source": self.source,
            "colour_step": self.colour_step,
            "colour_limit": self.colour_limit,
            "tile_px": self.tile_px,
            "skirt_factor": SKIRT_FACTOR,
            "flat_weight": FLAT_WEIGHT,
            "prior_count": PRIOR_COUNT,
        }

    def save(self, path: Path | str) -> Path:
        """Write the table as a versioned .npz, atomically."""
        path = Path(path)
        if path.is_dir():
            raise GelSightLUTError(f"calibration output {path} is a folder: give a file name")

        def write(temporary: Path) -> None:
            # Through a file object, so that np.savez adds no ".npz" to another suffix.
            with temporary.open("wb") as file:
                np.savez(
                    file,
                    metadata=np.array(json.dumps(self.metadata())),
                    table_gx=self.table_gx,
                    table_gy=self.table_gy,
                )

        return write_atomically(path, write)

    @classmethod
    def load(cls, path: Path | str) -> GelSightLUT:
        """Read and check a calibration file; a GelSightLUTError says what is wrong with it."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"calibration {path} does not exist")
        try:
            with np.load(path) as data:
                if "metadata" not in data.files:
                    raise GelSightLUTError(
                        f"calibration {path} has no metadata: not a touchshape GelSight calibration"
                    )
                meta = json.loads(str(data["metadata"]))
                table_gx = np.asarray(data["table_gx"])
                table_gy = np.asarray(data["table_gy"])
        except (zipfile.BadZipFile, OSError, EOFError, KeyError, ValueError) as error:
            if isinstance(error, GelSightLUTError):
                raise
            raise GelSightLUTError(
                f"calibration {path} is corrupt or not a touchshape GelSight calibration"
                f" (.npz): {error}"
            ) from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
            raise GelSightLUTError(f"calibration {path} is not a {FORMAT_NAME} file")
        if meta.get("version") != FORMAT_VERSION:
            raise GelSightLUTError(
                f"calibration {path} has format version {meta.get('version')}; this touchshape"
                f" reads version {FORMAT_VERSION}: calibrate again"
            )
        try:
            lut = cls(
                table_gx=table_gx.astype(np.float32, copy=False),
                table_gy=table_gy.astype(np.float32, copy=False),
                image_shape=(int(meta["image_height_px"]), int(meta["image_width_px"])),
                mm_per_px=float(meta["mm_per_px"]),
                ball_radius_mm=float(meta["ball_radius_mm"]),
                frames=tuple(str(f) for f in meta["frames"]),
                source=str(meta["source"]),
                colour_step=int(meta["colour_step"]),
                colour_limit=int(meta["colour_limit"]),
                tile_px=int(meta["tile_px"]),
            )
        except (KeyError, TypeError, ValueError) as error:
            raise GelSightLUTError(f"calibration {path}: bad metadata ({error})") from None
        lut.validate(str(path))
        return lut

    def validate(self, name: str = "lookup table") -> None:
        """Check that tables and metadata agree (sizes, finite values, positive scales)."""
        if min(self.image_shape) < 2 or self.mm_per_px <= 0 or self.ball_radius_mm <= 0:
            raise GelSightLUTError(f"{name}: image size and scales must be positive")
        if self.colour_step <= 0 or self.colour_limit < self.colour_step or self.tile_px <= 0:
            raise GelSightLUTError(f"{name}: bad colour binning or tile size")
        expected = self.tile_count * self.levels**3
        for label, table in (("table_gx", self.table_gx), ("table_gy", self.table_gy)):
            if table.shape != (expected,):
                raise GelSightLUTError(
                    f"{name}: {label} has shape {table.shape}, the metadata implies ({expected},)"
                    " - the file is corrupt or mismatched"
                )
            if not np.all(np.isfinite(table)):
                raise GelSightLUTError(f"{name}: {label} has non-finite values (corrupt)")


def sphere_gradients(
    shape: tuple[int, int],
    centre_px: tuple[float, float],
    contact_radius_px: float,
    ball_radius_px: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Analytic dh/dx, dh/dy of a ball's cap inside its contact circle (0 outside), and the mask.

    The indentation is h = const + sqrt(R^2 - rho^2), so dh/dx = -(x - cx) / sqrt(R^2 - rho^2).
    """
    rows, cols = np.indices(shape, dtype=np.float64)
    dx, dy = cols - centre_px[0], rows - centre_px[1]
    rho2 = dx * dx + dy * dy
    inside = rho2 < contact_radius_px**2
    root = np.sqrt(np.maximum(ball_radius_px**2 - rho2, 1e-12))
    return np.where(inside, -dx / root, 0.0), np.where(inside, -dy / root, 0.0), inside


def build_lut(
    presses: Sequence[BallPress],
    reference_bgr: ImageBGR,
    *,
    ball_radius_mm: float,
    mm_per_px: float,
    source: str = "",
) -> GelSightLUT:
    """Build the position-aware lookup table from ball presses and the no-contact frame.

    Every press contributes its contact-circle pixels (analytic sphere-cap gradients, weight 1)
    and its pixels beyond SKIRT_FACTOR contact radii (flat, weight FLAT_WEIGHT); each tile's
    table is the Gaussian-weighted (over pixel position, width TILE_PX) mean per colour, shrunk
    toward the whole-pad mean. Colours never seen map to zero slope.
    """
    if not presses:
        raise GelSightLUTError("no presses to calibrate from: the frame list is empty")
    check_image(reference_bgr, "reference image")
    shape = reference_bgr.shape[:2]
    if ball_radius_mm <= 0 or mm_per_px <= 0:
        raise GelSightLUTError("ball radius and mm per pixel must be positive")
    ball_radius_px = ball_radius_mm / mm_per_px
    level_lut, levels = colour_level_luts(COLOUR_STEP, COLOUR_LIMIT)
    colours = levels**3
    _, tile_rows, tile_cols = tile_grid(shape, TILE_PX)
    cells, cell_rows, cell_cols = tile_grid(shape, _CELL_PX)
    reference_shifted = 255 - reference_bgr.astype(np.int16)
    rows, cols = np.indices(shape)

    keys, sums_x, sums_y, weights = [], [], [], []
    for press in presses:
        check_image(press.image_bgr, f"press {press.name}", shape)
        if not 0 < press.radius_px < ball_radius_px:
            raise GelSightLUTError(
                f"press {press.name}: contact radius {press.radius_px} px must lie in (0,"
                f" {ball_radius_px:.1f}) px, the ball's radius"
            )
        gx, gy, inside = sphere_gradients(shape, press.centre_px, press.radius_px, ball_radius_px)
        rho2 = (cols - press.centre_px[0]) ** 2 + (rows - press.centre_px[1]) ** 2
        flat = rho2 > (SKIRT_FACTOR * press.radius_px) ** 2
        used = inside | flat
        shifted = press.image_bgr + reference_shifted  # image - reference + 255, in [0, 510]
        colour = (
            level_lut[shifted[..., 0]] * levels + level_lut[shifted[..., 1]]
        ) * levels + level_lut[shifted[..., 2]]
        weight = np.where(inside, 1.0, FLAT_WEIGHT)[used]
        keys.append(cells[used].astype(np.int64) * colours + colour[used])
        sums_x.append(gx[used] * weight)
        sums_y.append(gy[used] * weight)
        weights.append(weight)

    key = np.concatenate(keys)
    cell_of, colour_of = np.divmod(key, colours)

    def per_cell(values: list[NDArray[np.float64]]) -> scipy.sparse.csr_matrix:
        # Duplicate (cell, colour) entries are summed on conversion.
        return scipy.sparse.csr_matrix(
            (np.concatenate(values), (cell_of, colour_of)), shape=(cell_rows * cell_cols, colours)
        )

    cell_x, cell_y, cell_w = per_cell(sums_x), per_cell(sums_y), per_cell(weights)

    # Gaussian weight of each cell for each tile, by the distance between their centres.
    tile_r, tile_c = np.divmod(np.arange(tile_rows * tile_cols), tile_cols)
    cell_r, cell_c = np.divmod(np.arange(cell_rows * cell_cols), cell_cols)
    distance2 = ((tile_r[:, None] + 0.5) * TILE_PX - (cell_r[None, :] + 0.5) * _CELL_PX) ** 2
    distance2 += ((tile_c[:, None] + 0.5) * TILE_PX - (cell_c[None, :] + 0.5) * _CELL_PX) ** 2
    mixing = np.exp(-distance2 / (2.0 * TILE_PX**2))
    mixing[mixing < 1e-3] = 0.0  # beyond ~3.7 sigma: keeps the product sparse
    mixing = scipy.sparse.csr_matrix(mixing)

    total_w = np.asarray(cell_w.sum(axis=0)).ravel()
    seen = total_w > 0
    safe_w = np.where(seen, total_w, 1.0)
    pad_x = np.asarray(cell_x.sum(axis=0)).ravel() / safe_w
    pad_y = np.asarray(cell_y.sum(axis=0)).ravel() / safe_w
    tile_w = (mixing @ cell_w).toarray() + PRIOR_COUNT
    table_x = ((mixing @ cell_x).toarray() + PRIOR_COUNT * pad_x) / tile_w
    table_y = ((mixing @ cell_y).toarray() + PRIOR_COUNT * pad_y) / tile_w
    # A colour no press showed anywhere says nothing: read it as flat.
    table_x[:, ~seen] = 0.0
    table_y[:, ~seen] = 0.0
    lut = GelSightLUT(
        table_gx=table_x.astype(np.float32).ravel(),
        table_gy=table_y.astype(np.float32).ravel(),
        image_shape=(int(shape[0]), int(shape[1])),
        mm_per_px=float(mm_per_px),
        ball_radius_mm=float(ball_radius_mm),
        frames=tuple(p.name for p in presses),
        source=source,
        colour_step=COLOUR_STEP,
        colour_limit=COLOUR_LIMIT,
        tile_px=TILE_PX,
    )
    lut.validate()
    return lut


def build_lut_from_datapack(
    pack: DataPack,
    frames: Sequence[int],
    *,
    ball_radius_mm: float = DATAPACK_BALL_RADIUS_MM,
    mm_per_px: float = DATAPACK_MM_PER_PX,
    source: str = "",
) -> GelSightLUT:
    """:func:`build_lut` on frames of a dataPack, against its no-contact frame ``f0``."""
    if not frames:
        raise GelSightLUTError("no presses to calibrate from: the frame list is empty")
    return build_lut(
        [pack.press(i) for i in frames],
        pack.reference_bgr,
        ball_radius_mm=ball_radius_mm,
        mm_per_px=mm_per_px,
        source=source,
    )
