"""Generated shape families: watertight, reproducible from a seed, sized 3-30 cm."""

from __future__ import annotations

import numpy as np
import pytest

from models.families import FAMILIES, HELD_OUT_FAMILIES, SIZE_RANGE_M, make_family_shape
from models.shapes import ShapeError


@pytest.mark.parametrize("family", FAMILIES)
def test_family_shapes_are_watertight_sized_and_on_the_table(family: str) -> None:
    for seed in range(4):
        mesh = make_family_shape(family, np.random.default_rng((5, seed)))
        assert mesh.is_watertight and mesh.is_volume
        assert SIZE_RANGE_M[0] - 1e-6 <= mesh.extents.max() <= SIZE_RANGE_M[1] + 1e-6
        low, high = mesh.bounds
        assert low[2] == pytest.approx(0.0, abs=1e-9)  # standing on the table
        assert np.allclose((low[:2] + high[:2]) / 2, 0.0, atol=1e-9)  # centred on the object point


@pytest.mark.parametrize("family", FAMILIES)
def test_a_seed_reproduces_a_family_shape(family: str) -> None:
    first = make_family_shape(family, np.random.default_rng(11))
    again = make_family_shape(family, np.random.default_rng(11))
    other = make_family_shape(family, np.random.default_rng(12))
    assert np.array_equal(first.vertices, again.vertices)
    assert not np.array_equal(first.extents, other.extents)


def test_held_out_families_are_families_and_unknown_ones_are_refused() -> None:
    assert set(HELD_OUT_FAMILIES) < set(FAMILIES)
    with pytest.raises(ShapeError, match="unknown shape family 'teapot'"):
        make_family_shape("teapot", np.random.default_rng(0))


def test_a_vessel_has_its_handle_standing_out_of_its_body() -> None:
    # The handle (and a spout) stick out along x from a revolved body, round in y.
    for seed in range(8):
        mesh = make_family_shape("vessel", np.random.default_rng((5, seed)))
        assert mesh.extents[0] > 1.08 * mesh.extents[1]
