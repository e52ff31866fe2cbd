"""Precomputed maps from any model (`--predictor files:DIR`), in the layouts real models write.

- `matspray`: `{view}_basecolor.png` (or `_albedo`), `{view}_roughness.png`, `{view}_metallic.png`,
  optional `{view}_confidence.png`; matched to views by name. MatSpray's own `materials2d/` and its release.
- `marigold`: Marigold-IID appearance output, `{name}_albedo.npy|.png` and `{name}_material.npy|.png`
  with roughness in R and metallic in G; matched by name.
- `diffusionrenderer-svd`: `{video}/{chunk:04d}.{frame:04d}.{pass}.png`, passes `basecolor`, `roughness`,
  `metallic` (scalar passes as 3-channel PNG); frames map to the views in order.
- `diffusionrenderer-cosmos`: `gbuffer_frames/{clip}/{chunk}.{i:04d}.{pass}.jpg`; frames in order.
Several videos/clips are taken in natural order of their names, then by chunk and frame.

Normals, in the two named layouts: `{view}_normal.png` (8 or 16 bit, stored n * 0.5 + 0.5; black or alpha-0
pixels hold none) or `{view}_normal.exr|.npy` (the vectors), beside the maps. Their space is the view's camera
in MatSpray's convention (OpenCV: x right, y down, z forward) unless the folder's `predictor.json` says
`"normal_space"`: `"world"`, `"camera"`, or `"camera-opengl"` (x right, y up, z towards the viewer, as
Marigold's normals; turned into ours on reading). Nearly every normal of a map faces its camera in the map's own
space and far fewer in a wrong one, so a folder whose normals fit another space much better than the one it
says (or, saying none, MatSpray's camera axes) is refused with the space they fit, or, when its predictor.json
names the space, warned of. The frame layouts' normal passes are not read: their axis convention is not pinned
down here.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from torch import Tensor
from tqdm import tqdm

from matspray.data.scene import View
from matspray.errors import file_error
from matspray.predictors.base import Predictor
from matspray.predictors.encodings import check_encoding, decode_basecolor
from matspray.predictors.mapfile import (
    MAP_SUFFIXES,
    read_color_map,
    read_normal_map,
    read_packed_map,
    read_scalar_map,
)
from matspray.predictors.maps import INFO_FILE, MaterialMaps
from matspray.predictors.normalmaps import camera_to_world, facing_counts, from_opengl_camera

SUFFIX_PREFERENCE = (
    ".npy",
    ".exr",
    ".png",
    ".jpg",
    ".jpeg",
)  # when one map exists in several files: most precise first
FRAME_PASSES = ("basecolor", "roughness", "metallic")
# what a folder's info file may say its normal files are in -> (MaterialMaps.normal_space, flip from OpenGL axes)
SOURCE_NORMAL_SPACES = {"camera": ("camera", False), "camera-opengl": ("camera", True), "world": ("world", False)}
# shares of a folder's normals that face their cameras: below MISREAD in the folder's space while another space
# reaches FITS means the folder's space is not the files' (read in their own space, nearly all normals face it)
MISREAD_SHARE, FITS_SHARE = 0.75, 0.9
FACING_PIXELS = 128  # the facing check reads every k-th row and column, k = height // this (cost, not accuracy)


@dataclass
class Entry:
    """The files of one view (named layouts) or one video frame (ordered layouts)."""

    key: str  # view name, or "{clip}/{chunk}.{frame}"
    files: dict[str, Path]  # basecolor, roughness, metallic, confidence, normal, or material (roughness + metallic)


@dataclass
class Layout:
    name: str
    pattern: str  # what its files look like, for messages
    default_encoding: str  # of base color
    ordered: bool  # entries map to views in order (else by name)
    scan: Callable[[Path], list[Entry]]  # [] when the folder does not hold this layout


def natural_key(text: str) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", text)]


def _keep_preferred(files: dict[str, Path], channel: str, path: Path) -> None:
    current = files.get(channel)
    rank = SUFFIX_PREFERENCE.index
    if current is None or rank(path.suffix.lower()) < rank(current.suffix.lower()):
        files[channel] = path


def _scan_named(root: Path, pattern: re.Pattern, synonyms: dict[str, str]) -> dict[str, dict[str, Path]]:
    groups: dict[str, dict[str, Path]] = {}
    for path in sorted(root.iterdir()):
        match = pattern.match(path.name)
        if not match or not path.is_file() or path.suffix.lower() not in MAP_SUFFIXES:
            continue
        channel = synonyms.get(match.group("pass").lower(), match.group("pass").lower())
        _keep_preferred(groups.setdefault(match.group("name"), {}), channel, path)
    return groups


_MATSPRAY = re.compile(
    r"^(?P<name>.+)_(?P<pass>basecolor|albedo|roughness|metallic|confidence|normals?)\.[A-Za-z]+$", re.IGNORECASE
)
_MARIGOLD = re.compile(r"^(?P<name>.+)_(?P<pass>albedo|material|normals?)\.[A-Za-z]+$", re.IGNORECASE)
NAMED_SYNONYMS = {"albedo": "basecolor", "normals": "normal"}
_FRAME = re.compile(r"^(?P<chunk>\d+)\.(?P<frame>\d+)\.(?P<pass>[A-Za-z_]+)\.(?:png|jpe?g)$", re.IGNORECASE)


def scan_matspray(root: Path) -> list[Entry]:
    groups = _scan_named(root, _MATSPRAY, NAMED_SYNONYMS)
    if not any("roughness" in files or "metallic" in files for files in groups.values()):
        return []
    return [Entry(name, files) for name, files in groups.items()]


def scan_marigold(root: Path) -> list[Entry]:
    groups = _scan_named(root, _MARIGOLD, NAMED_SYNONYMS)
    if not any("material" in files for files in groups.values()):
        return []
    return [Entry(name, files) for name, files in groups.items()]


def _scan_frames(root: Path, cosmos: bool) -> list[Entry]:
    """Frames `{chunk}.{frame}.{pass}.{png|jpg}` anywhere under root; Cosmos output lies in `gbuffer_frames/`."""
    if root.name != "gbuffer_frames" and (root / "gbuffer_frames").is_dir():
        root = root / "gbuffer_frames"
    under_gbuffer = "gbuffer_frames" in root.resolve().parts
    frames: dict[tuple, dict[str, Path]] = {}
    for path in root.rglob("*"):
        match = _FRAME.match(path.name)
        if not match or match.group("pass").lower() not in FRAME_PASSES or not path.is_file():
            continue
        if cosmos != (under_gbuffer or "gbuffer_frames" in path.relative_to(root).parts):
            continue
        clip = path.parent.relative_to(root).as_posix()
        key = (
            tuple(natural_key(clip)),
            int(match.group("chunk")),
            int(match.group("frame")),
            clip,
            match.group("chunk"),
            match.group("frame"),
        )
        _keep_preferred(frames.setdefault(key, {}), match.group("pass").lower(), path)
    return [
        Entry(f"{key[3]}/{key[4]}.{key[5]}", files) for key, files in sorted(frames.items(), key=lambda kv: kv[0][:3])
    ]


LAYOUTS = (
    Layout(
        "marigold",
        "{name}_albedo.npy|png + {name}_material.npy|png (R roughness, G metallic)",
        "srgb",
        False,
        scan_marigold,
    ),
    Layout(
        "matspray",
        "{view}_basecolor.png (or _albedo) + {view}_roughness.png + {view}_metallic.png",
        "srgb",
        False,
        scan_matspray,
    ),
    Layout(
        "diffusionrenderer-cosmos",
        "gbuffer_frames/{clip}/{chunk}.{i:04d}.{basecolor|roughness|metallic}.jpg",
        "gamma1.8",
        True,
        lambda root: _scan_frames(root, cosmos=True),
    ),
    Layout(
        "diffusionrenderer-svd",
        "{video}/{chunk:04d}.{frame:04d}.{basecolor|roughness|metallic}.png",
        "gamma1.8",
        True,
        lambda root: _scan_frames(root, cosmos=False),
    ),
)


def detect_layout(root) -> tuple[Layout, list[Entry]]:
    """The first layout (in LAYOUTS order) whose files are in `root`, with its entries."""
    root = Path(root)
    if not root.is_dir():
        raise file_error(
            root,
            "is not a folder" if root.exists() else "does not exist",
            "files:DIR needs the folder holding the maps",
        )
    for layout in LAYOUTS:
        entries = layout.scan(root)
        if entries:
            return layout, entries
    seen = sorted(p.name for p in root.iterdir())[:5]
    tried = "; ".join(f"{layout.name}: {layout.pattern}" for layout in LAYOUTS)
    raise file_error(
        root, f"no known map layout found (tried {tried})", f"found {', '.join(seen) or 'an empty folder'}"
    )


def _list(items: list[str], limit: int = 10) -> str:
    return ", ".join(items[:limit]) + (f" and {len(items) - limit} more" if len(items) > limit else "")


class FilesPredictor(Predictor):
    """Reads maps another program computed; the layout is detected when it is created."""

    name = "files"

    def __init__(self, root, basecolor_encoding: str | None = None, notify: Callable[[str], None] = print):
        self.root = Path(root)
        self.layout, self.entries = detect_layout(self.root)
        self.basecolor_encoding = check_encoding(basecolor_encoding or self.layout.default_encoding)
        self.notify = notify
        self._check_complete()
        self.source_info = self._read_source_info()
        self.simulated = bool(
            self.source_info.get("simulated", False)
        )  # maps copied from a simulated run stay labelled
        self.benchmark_only = bool(self.source_info.get("benchmark_only", False))
        self.normal_space = self._source_normal_space()

    def describe(self) -> dict:
        info = dict(
            super().describe(),
            source=str(self.root),
            layout=self.layout.name,
            basecolor_encoding=self.basecolor_encoding,
        )
        if self.source_info:
            info["source_predictor"] = self.source_info
        if any("normal" in entry.files for entry in self.entries):
            info["source_normal_space"] = self.normal_space
        return info

    def _read_source_info(self) -> dict:
        """The folder's predictor.json (a MatSpray materials2d folder's, or one written beside another model's
        maps to say what they are), else {}."""
        path = self.root / INFO_FILE
        if not path.is_file():
            return {}
        try:
            info = json.loads(path.read_text())
        except (json.JSONDecodeError, OSError, UnicodeDecodeError):
            return {}
        return info if isinstance(info, dict) else {}

    def _source_normal_space(self) -> str:
        """The space of the folder's normal files (a key of SOURCE_NORMAL_SPACES): its info file's
        `normal_space`, else the view's camera in MatSpray's convention."""
        space = self.source_info.get("normal_space", "camera")
        if space not in SOURCE_NORMAL_SPACES:
            raise file_error(
                self.root / INFO_FILE,
                f"says normal_space {space!r}; use one of {', '.join(SOURCE_NORMAL_SPACES)}",
            )
        return space

    def _check_complete(self) -> None:
        needed = ("basecolor", "material") if self.layout.name == "marigold" else ("basecolor", "roughness", "metallic")
        incomplete = {}
        for entry in self.entries:
            lacking = [c for c in needed if c not in entry.files]
            if lacking:
                incomplete.setdefault(", ".join(lacking), []).append(entry.key)
        if incomplete:
            problems = "; ".join(f"no {lacking} for {_list(keys)}" for lacking, keys in incomplete.items())
            raise file_error(self.root, f"incomplete {self.layout.name} maps: {problems}")

    def assign(self, views: list[View]) -> dict[str, Entry]:
        """Which entry belongs to which view: by order for video layouts, by name otherwise."""
        if self.layout.ordered:
            if len(self.entries) != len(views):
                raise file_error(
                    self.root,
                    f"holds {len(self.entries)} {self.layout.name} frames but there are {len(views)} views",
                    "frames map to the views in order, so their numbers must match; "
                    "run the model on exactly these views",
                )
            clips = sorted({e.key.rsplit("/", 1)[0] for e in self.entries}, key=natural_key)
            if len(clips) > 1:
                self.notify(f"notice: frames of {len(clips)} clips taken in this order: {_list(clips, 6)}")
            return {view.name: entry for view, entry in zip(views, self.entries)}
        by_name = {entry.key: entry for entry in self.entries}
        missing = [v.name for v in views if v.name not in by_name]
        if missing:
            raise file_error(
                self.root,
                f"no {self.layout.name} maps for {len(missing)} of {len(views)} views: {_list(missing)}",
                f"maps are matched by view name; the folder has maps for {_list(sorted(by_name, key=natural_key), 4)}",
            )
        return {view.name: by_name[view.name] for view in views}

    def read_entry(self, entry: Entry) -> MaterialMaps:
        files = entry.files
        stored = read_color_map(files["basecolor"])
        if "material" in files:
            scalars = read_packed_map(files["material"], ("roughness", "metallic"))
            sources = {"roughness": files["material"], "metallic": files["material"]}
        else:
            scalars = {c: read_scalar_map(files[c], c) for c in ("roughness", "metallic")}
            sources = {c: files[c] for c in ("roughness", "metallic")}
        if "confidence" in files:
            scalars["confidence"] = read_scalar_map(files["confidence"], "confidence")
            sources["confidence"] = files["confidence"]
        normals = read_normal_map(files["normal"]) if "normal" in files else None  # [H, W, 3]
        sizes = dict(scalars) if normals is None else dict(scalars, normal=normals)
        for channel, values in sizes.items():
            if values.shape[:2] != stored.shape[:2]:
                raise file_error(
                    sources.get(channel, files.get(channel)),
                    f"is {values.shape[1]}x{values.shape[0]} but its base color {files['basecolor'].name} is "
                    f"{stored.shape[1]}x{stored.shape[0]}",
                )
        space, flip = SOURCE_NORMAL_SPACES[self.normal_space]
        if normals is not None and flip:
            normals = from_opengl_camera(normals)
        basecolor: Tensor = decode_basecolor(stored, self.basecolor_encoding)
        return MaterialMaps(
            basecolor, scalars["roughness"], scalars["metallic"], scalars.get("confidence"), normals, space
        )

    def predict(self, views: list[View]) -> dict[str, MaterialMaps]:
        assigned = self.assign(views)
        maps = {
            name: self.read_entry(entry)
            for name, entry in tqdm(assigned.items(), desc=f"reading {self.layout.name} maps", unit="view")
        }
        with_normals = [view for view in views if maps[view.name].normals is not None]
        if with_normals:
            self._check_normal_space(maps, with_normals)
            if len(with_normals) < len(views):
                lacking = [view.name for view in views if maps[view.name].normals is None]
                self.notify(
                    f"notice: {self.root}: normal maps for {len(with_normals)} of {len(views)} views; "
                    f"none for {_list(lacking)}, whose normals are left out"
                )
        return maps

    def _facing_shares(self, maps: dict[str, MaterialMaps], views: list[View]) -> dict[str, float]:
        """{space of SOURCE_NORMAL_SPACES: share of the views' normals that face their cameras read in it}."""
        said_flip = SOURCE_NORMAL_SPACES[self.normal_space][1]
        counts = dict.fromkeys(SOURCE_NORMAL_SPACES, (0, 0))
        for view in views:
            stored = maps[view.name].normals  # [h, w, 3] in the folder's space (OpenGL axes already turned)
            step = max(1, stored.shape[0] // FACING_PIXELS)
            raw = (from_opengl_camera(stored) if said_flip else stored)[::step, ::step]  # [h', w', 3] as in the files
            camera = view.camera.resized(stored.shape[1], stored.shape[0])
            rays = camera.pixel_directions().to(stored)[::step, ::step]  # [h', w', 3] world
            for source, (space, flip) in SOURCE_NORMAL_SPACES.items():
                normals = from_opengl_camera(raw) if flip else raw
                normals = camera_to_world(normals, camera) if space == "camera" else normals
                facing, total = facing_counts(normals, rays)
                counts[source] = (counts[source][0] + facing, counts[source][1] + total)
        return {source: facing / max(total, 1) for source, (facing, total) in counts.items()}

    def _check_normal_space(self, maps: dict[str, MaterialMaps], views: list[View]) -> None:
        """Refuses normal files that face their cameras in another space far more often than in the folder's: read
        in the wrong space (an unsaid space is MatSpray's camera axes) they would turn the Gaussians wrongly without a
        word. A space that predictor.json names is trusted, with a warning."""
        shares = self._facing_shares(maps, views)
        said = self.normal_space
        best = max(shares, key=shares.get)
        if shares[said] >= MISREAD_SHARE or shares[best] < FITS_SHARE:
            return
        found = (
            f"{shares[said]:.0%} of their normals face the camera when read as {said!r} normals, "
            f"{shares[best]:.0%} as {best!r} normals"
        )
        if "normal_space" in self.source_info:
            self.notify(f"warning: {self.root}: {found}; kept as {said!r}, as {INFO_FILE} says")
            return
        raise file_error(
            self.root,
            f"the normal maps do not look like normals in MatSpray's camera axes (x right, y down, z forward), what "
            f"a folder whose {INFO_FILE} names no normal_space holds: {found}",
            f'if they are {best!r} normals, say so in {self.root / INFO_FILE}: {{"normal_space": "{best}"}}; '
            f'camera-axes normals that point into the surface: "normal_space": "camera" there keeps them',
        )
