"""`web.page.write_page` makes the page's folder whole or not at all: its files appear together, an export that fails
half way leaves the page that was there before, and nothing of its own is left behind (`contents` would list its
staging folder)."""

import shutil

import pytest
import torch

import matspray.web.page as page_module
from matspray.method.asset import Asset
from matspray.method.relight import orbit_spec
from matspray.web.page import write_page
from tests.scenes import sky_map, sphere_cameras, sphere_of_disks

PAGE_FILES = {"index.html", "asset.js", "lights.js", "matspray-web.js", "LICENSES.txt"}


@pytest.fixture
def page_inputs(tmp_path, monkeypatch):
    """A small asset, its orbit, and a stand-in for the page's built script (the files are what is tested here)."""
    script = tmp_path / "build" / "built.js"
    script.parent.mkdir()
    script.write_text("// the page's script\n")
    monkeypatch.setattr(page_module, "BUNDLE", script)
    g, normals, materials = sphere_of_disks(200)
    spec = orbit_spec(sphere_cameras(6, 64), torch.zeros(3), (0.0, 0.0, 1.0))
    return Asset(g, materials, normals), spec


def contents(folder) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def test_the_page_is_written_whole_and_leaves_nothing_beside_it(tmp_path, page_inputs):
    asset, spec = page_inputs
    folder = tmp_path / "site" / "page"
    written = write_page(folder, asset, spec, sky_map())
    assert {p.name for p in written} == PAGE_FILES and written[-1].name == "index.html"
    assert set(contents(folder)) == PAGE_FILES
    assert sorted(p.name for p in folder.parent.iterdir()) == ["page"]


def test_the_page_goes_into_the_current_folder_when_given_dot(tmp_path, page_inputs, monkeypatch):
    asset, spec = page_inputs
    (tmp_path / "site").mkdir()
    monkeypatch.chdir(tmp_path / "site")
    write_page(".", asset, spec, sky_map())
    assert set(contents(tmp_path / "site")) == PAGE_FILES


def test_a_failed_export_leaves_the_page_before_it(tmp_path, page_inputs, monkeypatch):
    asset, spec = page_inputs
    folder = tmp_path / "page"
    write_page(folder, asset, spec, sky_map())
    (folder / "notes.txt").write_text("the user's own file")
    before = contents(folder)

    copies, copyfile = [], shutil.copyfile

    def copy_then_fail(source, target):  # the second copy (LICENSES.txt) fails, as a full disk would
        copies.append(target)
        if len(copies) == 2:
            raise OSError(28, "No space left on device")
        return copyfile(source, target)

    monkeypatch.setattr(page_module.shutil, "copyfile", copy_then_fail)
    smaller = Asset(asset.gaussians.subset(torch.arange(100)), asset.materials[:100], asset.normals[:100])
    with pytest.raises(OSError, match="No space left"):
        write_page(folder, smaller, spec, sky_map())
    assert contents(folder) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["build", "page"]

    monkeypatch.setattr(page_module.shutil, "copyfile", copyfile)
    write_page(folder, smaller, spec, sky_map())
    after = contents(folder)
    assert after["asset.js"] != before["asset.js"] and after["notes.txt"] == before["notes.txt"]
