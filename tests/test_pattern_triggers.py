"""Lava-pattern triggers of Randomized LavaWorld: specs, rotations, validation, chance finder."""

import numpy as np
import pytest

from rlbackdoors.triggers.pattern import (
    ARROWS,
    CROSS,
    LavaPattern,
    PatternTrigger,
    as_pattern_trigger,
    find_pattern,
)


def picture(p: LavaPattern) -> list[str]:
    """Rows north to south, '#' for lava."""
    g = p.grid()
    return ["".join("#" if g[x, y] else "." for x in range(3)) for y in range(3)]


def test_builtin_shapes():
    assert picture(CROSS) == [".#.", "###", ".#."]
    assert picture(ARROWS["north"]) == [".#.", "#.#", "..."]  # the paper's "up" arrow
    assert picture(ARROWS["east"]) == [".#.", "..#", ".#."]
    assert picture(ARROWS["south"]) == ["...", "#.#", ".#."]
    assert picture(ARROWS["west"]) == [".#.", "#..", ".#."]
    assert len(CROSS) == 5 and all(len(a) == 3 for a in ARROWS.values())


@pytest.mark.parametrize(
    "spec, n_rotations, cells",
    [
        ("cross", 1, 5),
        ("arrow", 4, 3),
        ("arrow:east", 1, 3),
        ("arrow:south", 1, 3),
        ("arrow:west", 1, 3),
        ("arrow:north", 1, 3),
        ("cells:0,0;1,1", 1, 2),
        ("cells:0,0;1,1:any", 4, 2),
        ("cells:0,0;2,2:any", 2, 2),  # a diagonal has two distinct rotations
        ("cells:1,1", 1, 1),
    ],
)
def test_spec_round_trip_and_rotations(spec, n_rotations, cells):
    t = PatternTrigger.parse(spec)
    assert PatternTrigger.parse(t.spec()) == t
    assert t.spec() == spec
    assert len(t.rotations()) == n_rotations and t.num_cells == cells
    assert len({r.cells for r in t.rotations()}) == n_rotations
    assert as_pattern_trigger(spec) == t and as_pattern_trigger(t) is t and as_pattern_trigger(None) is None


def test_equivalent_specs_are_equal():
    assert PatternTrigger.parse("arrow:any") == PatternTrigger.parse("arrow")
    assert PatternTrigger.parse("cells:1,0;0,1;1,1;2,1;1,2") == PatternTrigger.parse("cross")
    assert PatternTrigger.parse("cells:1,0;0,1;2,1:any") == PatternTrigger.parse("arrow")  # north arrow, any way
    assert PatternTrigger.parse("cells:1,0;0,1;2,1").spec() == "arrow:north"
    assert PatternTrigger.parse("cells:1,1:any") == PatternTrigger.parse("cells:1,1")  # rotation-invariant
    assert PatternTrigger.from_cells([(2, 1), (1, 0), (1, 2)]) == PatternTrigger.parse("arrow:east")
    assert as_pattern_trigger([(0, 0), (1, 1)]).spec() == "cells:0,0;1,1"
    assert as_pattern_trigger(CROSS).spec() == "cross"


def test_arrow_any_rotations_are_the_four_directions():
    rots = PatternTrigger.parse("arrow").rotations()
    assert {r.name for r in rots} == {f"arrow:{d}" for d in ("east", "south", "west", "north")}
    assert {r.cells for r in rots} == {a.cells for a in ARROWS.values()}


@pytest.mark.parametrize(
    "spec, message",
    [
        ("plus", "must be 'cross', 'arrow'"),
        ("arrow:up", "arrow direction 'up'"),
        ("cross:east", "no direction"),
        ("cells:", "at least one cell"),
        ("cells:0,0;0,0", "unique"),
        ("cells:0,3", "outside the 3x3 box"),
        ("cells:-1,0", "outside the 3x3 box"),
        ("cells:0,a", "not two integers"),
        ("cells:0,1,2", "DX,DY"),
    ],
)
def test_bad_specs_name_the_problem(spec, message):
    with pytest.raises(ValueError, match=message):
        PatternTrigger.parse(spec)


def test_bad_cell_lists():
    with pytest.raises(ValueError, match="at least one cell"):
        PatternTrigger.from_cells([])
    with pytest.raises(ValueError, match="unique"):
        PatternTrigger.from_cells([(1, 1), (1, 1)])
    with pytest.raises(ValueError, match="outside"):
        LavaPattern("x", ((3, 0),))
    with pytest.raises(ValueError, match="pair of integers"):
        PatternTrigger.from_cells([(1, 1, 1)])
    with pytest.raises(ValueError, match="pair of integers"):
        PatternTrigger.from_cells([(0.5, 1)])


def grid_with(cells, size=11) -> np.ndarray:
    g = np.zeros((size, size), dtype=bool)
    for c in cells:
        g[c] = True
    return g


def test_find_pattern_present_absent_and_rotations():
    cross_at = lambda cx, cy: [(cx, cy), (cx - 1, cy), (cx + 1, cy), (cx, cy - 1), (cx, cy + 1)]
    g = grid_with(cross_at(5, 5))
    assert find_pattern(g, "cross") == 1
    g2 = g.copy()
    g2[5, 4] = False  # one arm missing: no cross
    assert find_pattern(g2, "cross") == 0
    # extra lava around the cross does not hide it; a full 3x3 block contains one cross
    block = grid_with([(x, y) for x in range(4, 7) for y in range(4, 7)])
    assert find_pattern(block, "cross") == 1
    # a cross contains arrows in all four directions, one each
    assert find_pattern(g, "arrow") == 4
    for d in ("east", "south", "west", "north"):
        assert find_pattern(g, f"arrow:{d}") == 1
    # a single east arrow at the border of the room
    east = grid_with([(9, 2), (8, 1), (8, 3)])
    assert find_pattern(east, "arrow:east") == 1 and find_pattern(east, "arrow") == 1
    assert find_pattern(east, "arrow:north") == 0 and find_pattern(east, "cross") == 0
    # two disjoint arrows, and lists of cell sets
    two = east | grid_with([(2, 8), (1, 7), (3, 7)])  # plus a south arrow
    assert find_pattern(two, "arrow") == 2
    assert find_pattern(two, [ARROWS["south"].cells]) == 1
    assert find_pattern(two, ARROWS["south"]) == 1
    assert find_pattern(np.zeros((11, 11), bool), "cross") == 0


def test_find_pattern_is_translation_invariant_and_batched():
    # a pattern given away from the box corner counts placements the same
    g = grid_with([(3, 3), (4, 4)])
    assert find_pattern(g, [((1, 1), (2, 2))]) == find_pattern(g, [((0, 0), (1, 1))]) == 1
    batch = np.stack([g, grid_with([]), g | grid_with([(6, 6), (7, 7)])])
    assert find_pattern(batch, [((0, 0), (1, 1))]).tolist() == [1, 0, 2]
    with pytest.raises(ValueError, match="2-D"):
        find_pattern(np.zeros(5, bool), "cross")
