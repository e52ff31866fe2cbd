"""MatSpray's lat-long light as Blender shows it (benchmarks/blender_light.py): the guide's import step says to turn
the Environment Texture's vector half a turn about z, and this checks both that Blender shows the light turned
without it and that the turn puts it back. Needs Blender (`make test` installs it where it can)."""

from __future__ import annotations

import shutil

import pytest

from benchmarks.blender_light import blender_views

pytestmark = pytest.mark.skipif(
    shutil.which("blender") is None, reason="blender is not installed (Debian: apt install blender; `make test` tries)"
)


def brightest(views: dict, channel: int) -> str:
    return max(views, key=lambda name: views[name][channel])


@pytest.mark.slow  # four small Cycles renders, twice
def test_blender_shows_the_light_half_a_turn_about_up_and_the_guides_mapping_turns_it_back():
    plain = blender_views()
    assert (brightest(plain, 0), brightest(plain, 1)) == ("-x", "-y")  # red patch at +x, green at +y
    turned = blender_views(turn=180.0)
    assert (brightest(turned, 0), brightest(turned, 1)) == ("+x", "+y")
    for views in (plain, turned):  # the patches are seen in one view each, the rest is black
        assert sorted(red for red, _ in views.values())[-2] < 5 and sorted(g for _, g in views.values())[-2] < 5
        assert max(red for red, _ in views.values()) > 100 and max(g for _, g in views.values()) > 100
