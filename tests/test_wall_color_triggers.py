"""Wall-colour triggers of Colorful Memory: squares, specs, sampling, close-to-trigger, measuring."""

from collections import Counter

import numpy as np
import pytest
from minigrid.core.constants import COLOR_TO_IDX

from rlbackdoors.triggers.wall_colors import (
    COLORS,
    KINDS,
    WallColorTrigger,
    as_wall_color_trigger,
    chance_probability,
    check_close_k,
    close_to_trigger,
    distance,
    end_squares,
    kind_squares,
    matches,
    room_squares,
    sample,
)

END9 = "end:red,green,blue,purple,yellow,grey,red,green,blue"


def test_colours_are_minigrids():
    assert {c: i for i, c in enumerate(COLORS)} == COLOR_TO_IDX


def test_squares_size_7_are_the_spec_ones():
    # SPEC §3: far wall column hallway_end+2 = 6, plus (5, 0) and (5, 6); room (1..3, mid-2 = 1)
    assert end_squares(7) == ((5, 0), (6, 0), (6, 1), (6, 2), (6, 3), (6, 4), (6, 5), (6, 6), (5, 6))
    assert room_squares(7) == ((1, 1), (2, 1), (3, 1))
    assert kind_squares("end+room", 7) == end_squares(7) + room_squares(7)
    assert kind_squares("room+end", 7) == kind_squares("end+room", 7)


def test_squares_larger_sizes():
    assert end_squares(9) == ((7, 0), *((8, y) for y in range(9)), (7, 8))
    assert room_squares(9) == ((1, 2), (2, 2), (3, 2))
    assert len(end_squares(13)) == 15


@pytest.mark.parametrize(
    "spec",
    [
        END9,
        "room:grey,grey,red",
        "end+room:red,red,red,red,red,red,red,red,red;blue,green,yellow",
        "end:" + ",".join(["purple"] * 11),  # a size-9 end trigger
    ],
)
def test_spec_round_trip(spec):
    t = WallColorTrigger.parse(spec)
    assert t.spec() == spec and str(t) == spec
    assert WallColorTrigger.parse(t.spec()) == t
    assert as_wall_color_trigger(spec) == t and as_wall_color_trigger(t) is t and as_wall_color_trigger(None) is None


def test_equivalent_specs():
    both = WallColorTrigger.parse("end+room:red,red,red,red,red,red,red,red,red;blue,green,yellow")
    flat = "red,red,red,red,red,red,red,red,red,blue,green,yellow"
    assert WallColorTrigger.parse(f"end+room:{flat}") == both
    assert WallColorTrigger.parse("room+end:blue,green,yellow;red,red,red,red,red,red,red,red,red") == both
    assert WallColorTrigger.parse("room+end:blue,green,yellow,red,red,red,red,red,red,red,red,red") == both
    assert WallColorTrigger.parse(" ROOM: Gray , Red,BLUE ") == WallColorTrigger(room=(5, 0, 2))
    assert WallColorTrigger(room=("grey", "red", "blue")) == WallColorTrigger(room=(5, 0, 2))


def test_facts():
    t = WallColorTrigger.parse(END9)
    assert (t.kind, t.size, t.num_squares, t.num_patterns) == ("end", 7, 9, 10_077_696)
    assert t.colors == (0, 1, 2, 3, 4, 5, 0, 1, 2)
    assert t.cells(7)[0] == (5, 0, 0) and t.cells(7)[-1] == (5, 6, 2)
    r = WallColorTrigger.parse("room:red,green,blue")
    assert (r.kind, r.size, r.num_patterns) == ("room", None, 216)
    assert r.squares(9) == room_squares(9) and r.squares() == room_squares(7)
    both = WallColorTrigger(end=t.end, room=r.room)
    assert both.kind == "end+room" and both.num_patterns == 2_176_782_336
    assert both.with_colors([5] * 12) == WallColorTrigger(end=(5,) * 9, room=(5,) * 3)
    with pytest.raises(ValueError, match="11 colours given for a trigger of 12 squares"):
        both.with_colors([5] * 11)


@pytest.mark.parametrize(
    "spec, message",
    [
        ("end:red,pink,blue,red,red,red,red,red,red", r"end trigger colour 2 'pink' is not one of red, green, blue, purple, yellow, grey"),
        ("room:red,green", r"room trigger has 2 colours; it needs exactly 3"),
        ("room:red,green,blue,red", r"room trigger has 4 colours"),
        ("end:red,green,blue", r"end trigger has 3 colours; it needs size \+ 2"),
        ("end:" + ",".join(["red"] * 10), r"end trigger has 10 colours"),
        ("wall:red", r"must look like 'end:C,\.\.\.'"),
        ("end", r"names a kind but no colours.*sample\('end', seed\)"),
        ("end+room:", r"names a kind but no colours"),
        ("end+room:red;red;red", r"'end\+room:' takes end colours ';' room colours"),
        ("end+room:red,green", r"needs the end colours, then the 3 room colours"),
        ("room:red,,blue", r"room trigger colour 2 '' is not one of"),
    ],
)
def test_parse_errors_name_the_problem(spec, message):
    with pytest.raises(ValueError, match=message):
        WallColorTrigger.parse(spec)


def test_constructor_errors():
    with pytest.raises(ValueError, match="needs end colours, room colours or both"):
        WallColorTrigger()
    with pytest.raises(ValueError, match=r"room trigger colour 1 7 is not a colour index in 0\.\.5"):
        WallColorTrigger(room=(7, 0, 0))
    with pytest.raises(ValueError, match="must be a WallColorTrigger or a spec string"):
        as_wall_color_trigger(42)
    t = WallColorTrigger.parse(END9)
    with pytest.raises(ValueError, match=r"9x9 Colorful Memory's End Trigger has 11 squares"):
        t.check_size(9)
    with pytest.raises(ValueError, match=r"size=8 must be an odd integer >= 7"):
        t.check_size(8)
    with pytest.raises(ValueError, match="kind 'wall' is not one of end, room, end\\+room"):
        sample("wall", 0)


@pytest.mark.parametrize("kind, n", [("end", 9), ("room", 3), ("end+room", 12)])
def test_sample_kinds_and_seeds(kind, n):
    a = sample(kind, 3)
    assert a.kind == kind and a.num_squares == n
    assert sample(kind, 3) == a and sample(kind, np.random.default_rng(3)) == a
    assert WallColorTrigger.parse(kind, rng=3) == a and as_wall_color_trigger(kind, rng=3) == a
    assert len({sample(kind, s) for s in range(20)}) > 15
    assert sample(kind, 0, size=9).num_squares == n + (2 if "end" in kind else 0)
    with pytest.raises(ValueError, match="rng=-1 must be a non-negative integer seed"):
        sample(kind, -1)


def test_sample_is_uniform():
    """Each square's colour uniform over 6, squares independent (pairs uniform over 36)."""
    rng = np.random.default_rng(0)
    draws = np.array([sample("end+room", rng).colors for _ in range(6000)])
    for j in range(12):
        counts = np.bincount(draws[:, j], minlength=6)
        stat = ((counts - 1000) ** 2 / 1000).sum()
        assert stat < 25.7, (j, counts)  # chi-square(5), p = 1e-4
    pairs = np.bincount(draws[:, 0] * 6 + draws[:, 11], minlength=36)
    assert ((pairs - 6000 / 36) ** 2 / (6000 / 36)).sum() < 66.6  # chi-square(35), p = 1e-4


@pytest.mark.parametrize("k", [1, 2, 3])
def test_close_to_trigger_differs_in_exactly_k_squares(k):
    t = WallColorTrigger.parse("end+room:red,green,blue,purple,yellow,grey,red,green,blue;grey,grey,grey")
    rng = np.random.default_rng(k)
    which = Counter()
    new = Counter()
    for _ in range(3000):
        c = close_to_trigger(t, k, rng)
        assert c.kind == t.kind and c.size == t.size
        diff = [j for j in range(12) if c.colors[j] != t.colors[j]]
        assert len(diff) == k
        which.update(diff)
        new.update((c.colors[j] - t.colors[j]) % 6 for j in diff)
    expected = 3000 * k / 12
    assert sum((which[j] - expected) ** 2 / expected for j in range(12)) < 37.3  # chi-square(11), p = 1e-4
    assert set(new) == {1, 2, 3, 4, 5}  # the new colour is any *other* colour, uniformly
    e = 3000 * k / 5
    assert sum((new[d] - e) ** 2 / e for d in range(1, 6)) < 23.5


def test_close_to_trigger_errors():
    t = WallColorTrigger.parse("room:red,green,blue")
    assert close_to_trigger(t, 3, 0) != t
    for bad in (0, 4):
        with pytest.raises(ValueError, match=r"1 <= lo <= hi <= 3"):
            close_to_trigger(t, bad, 0)
    with pytest.raises(ValueError, match="must be an integer"):
        close_to_trigger(t, (1, 2), 0)
    assert check_close_k(2, 9) == (2, 2) and check_close_k((1, 3), 9) == (1, 3) and check_close_k([2, 9], 9) == (2, 9)
    for bad in ((3, 1), (0, 2), (1, 10), "1-3", (1.0, 2), True):
        with pytest.raises(ValueError, match="close_k"):
            check_close_k(bad, 9)


def blank_grid(size=7):
    g = np.zeros((size, size, 3), dtype=np.uint8)
    g[:, :, 0] = 1
    return g


def test_distance_and_matches_on_grids():
    t = WallColorTrigger.parse("end+room:red,green,blue,purple,yellow,grey,red,green,blue;grey,grey,red")
    g = blank_grid()
    assert distance(g, t) == 12 and not matches(g, t)
    for x, y, c in t.cells(7):
        g[x, y] = (2, c, 0)
    assert distance(g, t) == 0 and matches(g, t)
    batch = np.stack([g, g, g])
    batch[1, 1, 1, 1] = 0  # room square 1: red instead of grey
    batch[2, 6, 3] = (8, 3, 0)  # a goal of the right colour is not a wall
    assert distance(batch, t).tolist() == [0, 1, 1] and matches(batch, t).tolist() == [True, False, False]
    with pytest.raises(ValueError, match="square"):
        distance(np.zeros((7, 9, 3)), t)


def test_chance_probability_analytic():
    assert chance_probability("end") == 6.0**-9 == chance_probability(END9)
    assert chance_probability("room") == 1 / 216 == chance_probability("room:red,red,red")
    assert chance_probability("end+room") == 6.0**-12
    assert chance_probability("end", size=9) == 6.0**-11
    assert set(KINDS) == {"end", "room", "end+room"}
