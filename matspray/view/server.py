"""The viewer server: viser serves the page; MatSpray renders every picture and sends it as the scene's background.

One render thread per browser tab follows that tab's camera (`frames.Progressive`: small frames while it moves, one
full frame once it stops); what all tabs share (light, turn, exposure, display mode, variant, size) is one `ViewState`,
replaced whole on every change, so a frame never mixes two states. Frames render one at a time (a lock): on a CPU two
at once would only share the cores.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from matspray.errors import MatsprayError
from matspray.render.backend import rendering_with
from matspray.view.camera import camera_from_viser, viser_pose
from matspray.view.frames import BACKDROP, FrameSettings, Progressive, progressive_size, render_frame
from matspray.view.launch import Page, light_files, open_page
from matspray.view.lights import ESTIMATED, LightChoice, LightLoader, light_choices, unique_label
from matspray.view.scene import UP, open_run


@dataclass(frozen=True)
class ViewerConfig:
    host: str = "127.0.0.1"
    port: int = 8080
    env: tuple[str, ...] = ()  # --env files and folders
    resolution: int = 256  # long side of a still frame, pixels
    moving_scale: float = 0.5  # a frame while the camera moves is this fraction of the size
    settle: float = 0.25  # seconds without camera motion before the full frame


@dataclass(frozen=True)
class ViewState:
    """What every tab shows (the camera is each tab's own)."""

    variant: str
    light: str  # label of the light menu's entry
    turn: float = 0.0  # degrees about the up axis
    exposure: float = 0.0  # stops
    mode: str = "relit"
    resolution: int = 256
    glb: str = "hidden"  # glb.PLACES


def load_numba_kernels() -> None:
    from matspray.render.numba.backend import ensure_compiled

    ensure_compiled(np.float32)  # the assets' dtype


class Viewer:
    """`matspray view` as a library: `Viewer(run, config).start()` returns the URL; `stop()` ends it. `page`: a page
    opened already (`launch.open_page`, before torch was imported),
    which the viewer takes over instead of opening one."""

    def __init__(
        self,
        run_root,
        config: ViewerConfig = ViewerConfig(),
        device="cpu",
        backend: str = "torch",
        notify=None,
        page: Page | None = None,
    ):
        self.config, self.device, self.backend = config, torch.device(device), backend
        self.notify = notify or (lambda message: print(message, file=sys.stderr, flush=True))
        self.run = open_run(run_root, device=self.device, notify=self.notify)
        files = light_files(config.env)  # a missing --env path: ConfigError before anything starts
        self.workers: list[threading.Thread] = []  # the background threads that end on their own; stop() waits
        if backend == "numba":  # its compiled kernels load from numba's cache while the asset and the light are read
            self.start_worker(load_numba_kernels, "matspray-kernels")  # waits for a compilation already under way
        variant = self.run.variants[0]
        self.choices = light_choices(files, has_estimate=True)
        self.loader = LightLoader(self.device)
        first = ESTIMATED if self.run.estimated_light(variant) is not None else "studio"
        self.state = ViewState(variant=variant, light=first, resolution=config.resolution)
        try:
            self.light = self._load(first, variant)  # the last good light, unturned
        except MatsprayError as exc:  # an unreadable estimated light: said, and the viewer starts under a built-in
            self.notify(f"matspray view: {exc}; showing the built-in light 'studio' instead")
            self.state = dataclasses.replace(self.state, light="studio")
            self.light = self._load("studio", variant)
        self.page = page
        self.server = None
        self.gui = None
        self.views: dict[int, "ClientView"] = {}
        self.connected: set[int] = set()  # client ids whose view is made or being made
        self.render_lock = threading.Lock()
        self.state_lock = threading.RLock()
        self.uploads = tempfile.TemporaryDirectory(prefix="matspray-view-")
        self.start_camera = self.run.start_camera(variant)

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> str:
        from matspray.view.gui import Controls

        if self.page is None:
            self.page = open_page(self.config.host, self.config.port)
        self.server = self.page.server
        self.server.scene.set_up_direction(UP)
        wxyz, position, fov = viser_pose(self.start_camera)
        center, _ = self.run.object_frame(self.state.variant)
        initial = self.server.initial_camera
        initial.position, initial.look_at, initial.up, initial.fov = tuple(position), tuple(center), UP, fov
        self.gui = Controls(self)
        self.page.loading.remove()
        self.workers.append(self.run.load_photos())
        # the first frame's one-off costs (the rasterizer's compiled kernels loaded from their cache, first allocations)
        # are paid here, while the browser opens the page; a tab connected already waits for it on the render lock
        self.start_worker(self.render, "matspray-warmup", self.start_camera.scaled(0.25))
        self.server.on_client_connect(self._connect)  # also called now for the tabs that connected while the run loaded
        self.server.on_client_disconnect(self._disconnect)
        return self.url

    @property
    def url(self) -> str:
        return self.page.url if self.page else f"http://{self.config.host}:{self.config.port}"

    def start_worker(self, target, name: str, *args) -> threading.Thread:
        """`target(*args)` in a daemon thread that ends on its own, which stop() waits for."""
        thread = threading.Thread(target=target, args=args, daemon=True, name=name)
        self.workers.append(thread)
        thread.start()
        return thread

    def stop(self) -> None:
        for view in list(self.views.values()):
            view.stop()
        for view in list(self.views.values()):
            view.thread.join(timeout=10.0)  # a frame being rendered is not sent to a closed page
        # the warm-up render, the photos' and the kernels' loading: a daemon thread still inside torch or numba when
        # the interpreter exits aborts the process ("terminate called without an active exception"). This viewer's
        # own, not every matspray thread: another viewer's per-tab loops in this process run until that one stops.
        for thread in self.workers:
            if thread is not threading.current_thread():
                thread.join(timeout=60.0)
        if self.page is not None:
            self.page.stop()
            self.page = self.server = None
        self.uploads.cleanup()

    def _connect(self, client) -> None:
        with self.state_lock:  # viser may call this twice for a tab that connects while the handler is attached
            if client.client_id in self.connected:
                return
            self.connected.add(client.client_id)
        # a new tab starts at the start view: set here, before its first frame, because the page may report viser's
        # default camera before it has applied `initial_camera`
        wxyz, position, fov = viser_pose(self.start_camera)
        center, _ = self.run.object_frame(self.state.variant)
        with client.atomic():
            client.camera.up_direction = UP
            client.camera.position = tuple(position)
            client.camera.look_at = tuple(center)
            client.camera.fov = fov
        view = ClientView(self, client)
        self.views[client.client_id] = view
        view.start()

    def _disconnect(self, client) -> None:
        view = self.views.pop(client.client_id, None)
        self.connected.discard(client.client_id)
        if view is not None:
            view.stop()

    # ---------------------------------------------------------------- state
    def update(self, **changes) -> ViewState:
        """Change what every tab shows; each tab renders a full frame of the new state."""
        with self.state_lock:
            self.state = dataclasses.replace(self.state, **changes)
        for view in list(self.views.values()):
            view.changed()
        return self.state

    def choice(self, label: str) -> LightChoice:
        return next(c for c in self.choices if c.label == label)

    def _load(self, label: str, variant: str):
        choice = self.choice(label)
        if choice.spec is None:  # the run's estimated light: the variant's own envmap.exr
            path = self.run.estimated_light(variant)
            if path is None:
                raise MatsprayError(
                    f"{self.run.root}: variant '{variant}' learned no light (no envmap.exr); choose another light"
                )
            return self.loader.load(path)
        return self.loader.load(choice.spec)

    def set_light(self, label: str, variant: str | None = None) -> bool:
        """Show light `label` (and variant); on failure say why in one line, in the page and on the console, keep the
        last good light and return False."""
        variant = variant or self.state.variant
        try:
            light = self._load(label, variant)
        except MatsprayError as exc:
            self.tell(str(exc), title="light not changed")
            return False
        with self.state_lock:
            self.light = light
        self.update(light=label, variant=variant)
        if self.gui is not None:  # a change made here, not in the page, shows in the page's menus too
            self.gui.show(light=label, variant=variant)
        return True

    def add_light_file(self, path: Path) -> str | None:
        """A light file from the page's file picker: loaded first, added to the menu only when it loads. Its label."""
        label = unique_label(path.name, [c.label for c in self.choices])
        try:
            self.loader.load(path)
        except MatsprayError as exc:
            self.tell(str(exc), title="light not changed")
            return None
        self.choices.append(LightChoice(label, str(path)))
        return label

    def tell(self, message: str, title: str = "matspray view") -> None:
        """One line on the console and as a notification in every open page."""
        self.notify(f"matspray view: {message}")
        if self.server is not None:
            for client in self.server.get_clients().values():
                client.add_notification(title, message, color="red", auto_close_seconds=15.0)

    def frame_inputs(self):
        """(state, asset, turned light) to render now."""
        with self.state_lock:
            state, light = self.state, self.light
        return state, self.run.asset(state.variant), light.turned(math.radians(state.turn))

    def render(self, camera, state=None):
        """One frame for `camera` in the current (or given) state, with MatSpray's renderer, one at a time."""
        current, asset, light = self.frame_inputs()
        state = state or current
        with self.render_lock, rendering_with(self.backend):
            return render_frame(asset, camera.to(self.device), light, FrameSettings(state.mode, state.exposure))

    def snapshot(self, client) -> Path:
        """The client's view at full size, as shown, into RUN/view/."""
        from matspray.view.snapshot import write_snapshot

        view = self.views[client.client_id]
        state = self.state
        frame = self.render(view.camera(moving=False), state)
        return write_snapshot(self.run.snapshot_root, frame.image, state.variant, state.light, state.mode)


class ClientView:
    """One browser tab: follows its camera, renders progressively in its own thread, shows the frame time and the
    nearest training photo in its own panel."""

    def __init__(self, viewer: Viewer, client):
        self.viewer, self.client = viewer, client
        self.progressive = Progressive(settle=viewer.config.settle)
        self.wake = threading.Condition()
        self.running = True
        self.thread = threading.Thread(target=self._loop, name=f"matspray-view-{client.client_id}", daemon=True)
        self.last_frame = None
        self.photo_index = None
        self.status = client.gui.add_markdown("**frame** waiting for the first picture", order=100.0)
        self.photo = None
        client.camera.on_update(lambda _: self.moved())

    def start(self) -> None:
        self.moved()
        self.thread.start()

    def stop(self) -> None:
        with self.wake:
            self.running = False
            self.wake.notify_all()

    def moved(self) -> None:
        with self.wake:
            self.progressive.moved(time.monotonic())
            self.wake.notify_all()

    def changed(self) -> None:
        with self.wake:
            self.progressive.changed()
            self.wake.notify_all()

    def camera(self, moving: bool):
        cam = self.client.camera
        aspect = cam.image_width / max(cam.image_height, 1)
        state = self.viewer.state
        width, height = progressive_size(aspect, state.resolution, moving, self.viewer.config.moving_scale)
        return camera_from_viser(cam.wxyz, cam.position, cam.fov, width, height)

    def _loop(self) -> None:
        while True:
            with self.wake:
                while self.running:
                    kind = self.progressive.next(time.monotonic())
                    if kind is not None:
                        break
                    self.wake.wait(timeout=min(self.progressive.wait(time.monotonic()), 1.0))
                if not self.running:
                    return
                self.progressive.rendered(kind)  # a camera move during the render marks it pending again
            try:
                self._show(kind)
            except Exception as exc:  # noqa: BLE001 - a failed frame is reported; the tab keeps working
                self.viewer.tell(
                    f"rendering failed ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})", title="render"
                )
                time.sleep(1.0)

    def _show(self, kind: str) -> None:
        state = self.viewer.state
        if state.glb == "instead":  # the mesh in place of the Gaussians: nothing of ours behind it
            self.client.scene.set_background_image(np.full((8, 8, 3), round(255 * 0.25), np.uint8), format="png")
            self.status.content = "**frame** Gaussians hidden (glb shown instead)"
            return
        camera = self.camera(moving=kind == "low")
        frame = self.viewer.render(camera, state)
        if not self.running:  # the tab closed while this frame rendered
            return
        self.client.scene.set_background_image(frame.image, format="png")
        self.last_frame = frame
        width, height = frame.size
        what = "moving: low resolution" if kind == "low" else "still: full resolution"
        self.status.content = (
            f"**frame** {1000 * frame.seconds:.0f} ms at {width}x{height} ({what}) · "
            f"{self.viewer.backend} on {self.viewer.device.type}"
        )
        self._update_photo()

    def _update_photo(self) -> None:
        from matspray.view.photos import nearest_view, photo_image

        views = self.viewer.run.photos()
        if not views:
            return
        center, _ = self.viewer.run.object_frame(self.viewer.state.variant)
        index = nearest_view(
            np.stack([v.camera.center.double().cpu().numpy() for v in views]), center, self.client.camera.position
        )
        if index == self.photo_index:
            return
        self.photo_index = index
        image = photo_image(views[index], BACKDROP)
        if self.photo is None:
            self.photo = self.client.gui.add_image(
                image, label=f"nearest training photo: {views[index].name}", format="png", order=101.0
            )
        else:
            self.photo.image = image
            self.photo.label = f"nearest training photo: {views[index].name}"
