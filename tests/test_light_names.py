"""One name per light: the built-in lights and the packaged HDRIs have different names, and `relight --help`, the
viewer's menu and the error for an unknown name list the same set."""

from __future__ import annotations

import re

import pytest

from matspray.cli import build_parser
from matspray.errors import ConfigError
from matspray.presets import BUILTIN_LIGHTS, packaged_hdris
from matspray.render.shade.lights import BUILTINS, hdri_files, list_envmaps, load_envmap
from matspray.view.lights import light_choices


def named(text: str) -> list[str]:
    """The names of '(built-ins: a, b; HDRIs: c, d)' in a text, whitespace as help wraps it."""
    found = re.search(r"built-ins: ([^;)]*)(?:; HDRIs: ([^)]*))?\)", " ".join(text.split()))
    assert found, text
    return [name.strip() for group in found.groups() if group for name in group.split(",")]


def command_help(name: str) -> str:
    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return subparsers.choices[name].format_help()


def test_no_name_means_two_lights():
    assert list(BUILTINS) == list(BUILTIN_LIGHTS)
    assert not set(BUILTINS) & set(hdri_files()), "a packaged HDRI has a built-in light's name"
    assert hdri_files() == packaged_hdris()
    assert len(list_envmaps()) == len(set(list_envmaps())) == len(BUILTINS) + len(hdri_files())


def test_relight_help_the_viewers_menu_and_the_unknown_name_error_list_the_same_lights():
    with pytest.raises(ConfigError) as caught:
        load_envmap("moon")
    from_error = named(str(caught.value))
    from_help = named(command_help("relight"))
    from_view_help = named(command_help("view"))
    from_menu = [choice.label for choice in light_choices([], has_estimate=False)]
    assert sorted(from_error) == sorted(from_help) == sorted(from_view_help) == sorted(from_menu)
    assert sorted(from_menu) == sorted(list_envmaps())
    assert {"studio", "sunset", "studio-small", "venice-sunset", "forest"} <= set(from_menu)
    for name in from_menu:  # and each of them is a light the loaders read
        assert load_envmap(name, height=4)[1].shape == (4, 8, 3)
