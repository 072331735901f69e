"""`touchshape explore --object FILE` and `touchshape sim snapshot --object FILE` with a mesh the
bench cannot explore: one line naming the file and the reason, exit code 2, before any device
is connected; a mesh whose hole can be filled is taken with a warning."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from controller.cli.main import main
from controller.config import Config
from drivers.sim.world import SimWorld, min_object_extent_m

LIAR_PLY = (
    "ply\nformat ascii 1.0\nelement vertex 3\nproperty float y\nproperty float z\n"
    "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0\n1 0\n0 1\n3 0 1 2\n"
)


def write_bad_mesh(directory: Path, kind: str) -> Path:
    if kind == "liar":
        path = directory / "liar.ply"
        path.write_text(LIAR_PLY)
        return path
    meshes = {
        "huge": trimesh.creation.box((3.0, 3.0, 3.0)),
        "tiny": trimesh.creation.box((1e-5, 1e-5, 1e-5)),
        "triangle": trimesh.Trimesh([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]], [[0, 1, 2]]),
    }
    path = directory / f"{kind}.stl"
    meshes[kind].export(path)
    return path


REASONS = {
    "huge": "is too large for the workspace: 3.000 x 3.000 x 3.000 m, at most 0.260 m",
    "tiny": "is too small to touch: 0.01 x 0.01 x 0.01 mm, its largest side must be at least 19",
    "triangle": "is not a closed solid (3 open edges) and its holes could not be filled",
    "liar": "the header does not match the data (no field 'x')",
}


@pytest.mark.parametrize("kind", list(REASONS))
@pytest.mark.parametrize(
    "command", [["explore", "--touches", "1"], ["sim", "snapshot", "--out", "snapshot"]]
)
def test_a_mesh_the_bench_cannot_explore_gets_one_line_and_rc_2(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    kind: str,
    command: list[str],
) -> None:
    monkeypatch.chdir(tmp_path)  # the default config writes logs/ under the working directory
    path = write_bad_mesh(tmp_path, kind)
    assert main([*command, "--object", str(path)]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("touchshape: error:")]
    assert len(errors) == 1 and "Traceback" not in err, err
    assert str(path) in errors[0] and REASONS[kind] in errors[0], errors[0]
    assert not (tmp_path / "snapshot").exists()


def test_a_mesh_whose_hole_can_be_filled_builds_the_bench_with_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    box = trimesh.creation.box((0.06, 0.06, 0.06))
    path = tmp_path / "open_box.stl"
    trimesh.Trimesh(box.vertices, box.faces[box.face_normals[:, 2] < 0.9]).export(path)
    config = Config()
    sim = type(config.sim)(object=str(path))
    with caplog.at_level("WARNING"):
        world = SimWorld.from_config(
            sim, config.robot.arm, config.gripper, config.sensor, max_object_extent_m=0.26
        )
    assert world.object_mesh_world.is_volume
    np.testing.assert_allclose(world.object_mesh_world.bounds[:, 2], [0.0, 0.06], atol=1e-9)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warnings == [f"object {path} was not a closed solid: its holes were filled"]


def test_the_smallest_object_is_the_gel_pad() -> None:
    sensor = Config().sensor
    assert min_object_extent_m(sensor) == pytest.approx(0.019)
    bigger = type(sensor)(pad_width_mm=25.0)
    assert min_object_extent_m(bigger) == pytest.approx(0.025)
