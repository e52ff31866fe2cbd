"""What a run folder offers the viewer: its variants with an asset, each asset (read once, when first shown), the
training photos (read in the background: a capture can take seconds to load, the first picture must not wait), the
exported glb files, and a first camera that frames the object. A splats glb (`matspray export --splats`) offers its
one asset and its light: `open_run` opens either."""

from __future__ import annotations

import math
import tempfile
import threading
from pathlib import Path

import numpy as np
import torch

from matspray.data.camera import Camera
from matspray.errors import MatsprayError
from matspray.export.frames import find_glbs
from matspray.method.asset import Asset, read_asset
from matspray.rundir import RunDir
from matspray.view.launch import check_source, run_variants
from matspray.view.lights import ENVMAP_FILE, estimated_light_path

UP = (0.0, 0.0, 1.0)  # the dataset's world up (Blender / NeRF-synthetic, Z up)
START_FOV = math.radians(40.0)  # vertical field of view of the first camera when the photos are not loaded yet


class ViewerRun:
    """A run folder opened for viewing. Raises RunError (one line naming the command to run first) when `root` is no
    run folder or holds no asset."""

    def __init__(self, root, device="cpu", notify=print):
        self.variants = run_variants(root)
        self.root = Path(root)
        self.run = RunDir(self.root)
        self.device = torch.device(device)
        self.notify = notify
        self.glbs = find_glbs(root)
        self._assets: dict[str, Asset] = {}
        self._frames: dict[str, tuple[np.ndarray, float]] = {}
        self._lock = threading.Lock()
        self._views = None  # training views once loaded; [] when they cannot be
        self._views_ready = threading.Event()

    def asset(self, variant: str) -> Asset:
        with self._lock:
            if variant not in self._assets:
                self._assets[variant] = read_asset(self.run.asset_path(variant), device=self.device)
            return self._assets[variant]

    def estimated_light(self, variant: str) -> Path | None:
        return estimated_light_path(self.run.asset_path(variant))

    @property
    def snapshot_root(self) -> Path:  # snapshots go into its view/ folder
        return self.root

    # ---------------------------------------------------------------- photos
    def load_photos(self) -> threading.Thread:
        """Read the training views in a background thread (`photos()` answers once they are there); returns it."""
        thread = threading.Thread(target=self._load_photos, name="matspray-view-photos", daemon=True)
        thread.start()
        return thread

    def _load_photos(self) -> None:
        from matspray.data import load_run_scene

        try:
            scene = load_run_scene(self.run)
            self._views = list(scene.train)
        except (MatsprayError, OSError, KeyError) as exc:
            self._views = []
            self.notify(f"matspray view: no training photos to compare with ({exc})")
        finally:
            self._views_ready.set()

    def photos(self, wait: float | None = 0.0):
        """The training views, or None while they are still loading."""
        return self._views if self._views_ready.wait(wait) else None

    # ---------------------------------------------------------------- framing
    def object_frame(self, variant: str) -> tuple[np.ndarray, float]:
        """Centre [3] and radius of the object: the median of the Gaussians' centres and the 95th percentile of their
        distance from it (a few stray Gaussians far away must not shrink the object to a dot)."""
        if variant not in self._frames:
            means = self.asset(variant).gaussians.means.detach().double().cpu()
            center = means.median(dim=0).values
            radius = float(torch.quantile((means - center).norm(dim=-1), 0.95)) if len(means) else 1.0
            self._frames[variant] = (center.numpy(), max(radius, 1e-6))
        return self._frames[variant]

    def start_camera(self, variant: str, width: int = 256, height: int = 256) -> Camera:
        """A camera 25 degrees above the object's centre that fits the whole object in a 40 degree view."""
        center, radius = self.object_frame(variant)
        distance = 1.15 * radius / math.sin(0.5 * START_FOV)
        elevation, azimuth = math.radians(25.0), math.radians(-60.0)
        direction = np.array(
            [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
        )
        fov_x = 2 * math.atan(math.tan(0.5 * START_FOV) * width / height)
        return Camera.look_at(center + distance * direction, center, UP, fov_x, width, height)


class SplatsFileRun(ViewerRun):
    """A glb of `matspray export --splats` opened for viewing: its one asset (named by the file), its estimated light
    (written once to a temporary .exr, which the viewer's light loader reads as it reads a run's), no photos and no
    meshes. Raises RunError / DataError (one line naming the file) when it is no such file."""

    def __init__(self, path, device="cpu", notify=print):
        from matspray.export.splats import read_splats_asset

        path = Path(path)
        check_source(path)
        self.root = path
        self.device = torch.device(device)
        self.notify = notify
        self.splats = read_splats_asset(path, self.device)
        self.variants = [path.stem]
        self.glbs = []
        self._assets = {path.stem: self.splats.asset}
        self._frames: dict[str, tuple[np.ndarray, float]] = {}
        self._lock = threading.Lock()
        self._views, self._views_ready = [], threading.Event()
        self._views_ready.set()
        self._light_folder = tempfile.TemporaryDirectory(prefix="matspray-view-splats-")
        self._light = None

    def asset(self, variant: str) -> Asset:
        return self._assets[variant]

    def estimated_light(self, variant: str) -> Path | None:
        from matspray.data.images import write_image

        if self.splats.light is None:
            return None
        with self._lock:
            if self._light is None:
                self._light = Path(self._light_folder.name) / ENVMAP_FILE
                write_image(self._light, self.splats.light.float().cpu())
        return self._light

    @property
    def snapshot_root(self) -> Path:  # snapshots go beside the file, into its folder's view/
        return self.root.parent

    def load_photos(self) -> threading.Thread:  # the file holds none
        thread = threading.Thread(target=lambda: None, name="matspray-view-photos", daemon=True)
        thread.start()
        return thread


def open_run(root, device="cpu", notify=print) -> ViewerRun:
    """A run folder, or a splats .glb, opened for viewing."""
    if Path(root).suffix.lower() == ".glb":
        return SplatsFileRun(root, device, notify)
    return ViewerRun(root, device, notify)
