"""The page's controls (viser GUI), shared by every open tab, each bound to one `Viewer` method."""

from __future__ import annotations

import math
from pathlib import Path

from matspray.export.frames import dataset_from_glb
from matspray.view.frames import MODES
from matspray.view.glb import PLACES, glb_pose

RESOLUTIONS = (64, 1024)  # the still frame's long side, pixels


class Controls:
    def __init__(self, viewer):
        self.viewer = viewer
        gui = viewer.server.gui
        state = viewer.state
        self._reverting = False
        with gui.add_folder("Light"):
            self.light = gui.add_dropdown(
                "light",
                [c.label for c in viewer.choices],
                initial_value=state.light,
                hint="the run's estimated light, the built-in lights and the HDRIs given with --env",
            )
            self.upload = gui.add_upload_button(
                "open an HDRI (.exr, .hdr)",
                icon=None,
                mime_type="*/*",
                hint="a lat-long HDR panorama from this computer",
            )
            self.turn = gui.add_slider(
                "turn (degrees)",
                min=-180.0,
                max=180.0,
                step=1.0,
                initial_value=state.turn,
                hint="turns the light about the up axis",
            )
            self.exposure = gui.add_slider(
                "exposure (stops)", min=-6.0, max=6.0, step=0.1, initial_value=state.exposure
            )
        with gui.add_folder("Show"):
            self.mode = gui.add_dropdown(
                "display",
                MODES,
                initial_value=state.mode,
                hint="relit, relit with the light drawn behind, or a material map",
            )
            self.variant = gui.add_dropdown("variant", viewer.run.variants, initial_value=state.variant)
            self.resolution = gui.add_slider(
                "resolution (px)",
                min=RESOLUTIONS[0],
                max=RESOLUTIONS[1],
                step=32,
                initial_value=state.resolution,
                hint="long side of the still picture; half while moving",
            )
            self.glb = self.glb_file = None
            if viewer.run.glbs:
                self.glb_file = gui.add_dropdown(
                    "glb file", [p.name for p in viewer.run.glbs], initial_value=viewer.run.glbs[0].name
                )
                self.glb = gui.add_dropdown(
                    "glb",
                    PLACES,
                    initial_value=state.glb,
                    hint="the exported mesh, drawn by the browser with viser's own lighting",
                )
        self.snapshot = gui.add_button("snapshot (PNG into RUN/view/)")
        self.mesh = None

        self.light.on_update(lambda _: self._light())
        self.upload.on_upload(lambda event: self._upload(event.target.value))
        self.turn.on_update(lambda _: viewer.update(turn=float(self.turn.value)))
        self.exposure.on_update(lambda _: viewer.update(exposure=float(self.exposure.value)))
        self.mode.on_update(lambda _: viewer.update(mode=self.mode.value))
        self.variant.on_update(lambda _: self._variant())
        self.resolution.on_update(lambda _: viewer.update(resolution=int(self.resolution.value)))
        if self.glb is not None:
            self.glb.on_update(lambda _: self._glb())
            self.glb_file.on_update(lambda _: self._glb())
        self.snapshot.on_click(self._snapshot)

    def _set_quietly(self, handle, value) -> None:
        self._reverting = True
        try:
            handle.value = value
        finally:
            self._reverting = False

    def show(self, **values) -> None:
        """Set menus to `values` (e.g. light=..., variant=...) without acting on the change again."""
        for name, value in values.items():
            handle = getattr(self, name)
            if handle.value != value:
                self._set_quietly(handle, value)

    def _light(self) -> None:
        if self._reverting or self.light.value == self.viewer.state.light:
            return
        if not self.viewer.set_light(self.light.value):
            self._set_quietly(self.light, self.viewer.state.light)  # keep showing the last good light

    def _variant(self) -> None:
        if self._reverting or self.variant.value == self.viewer.state.variant:
            return
        # the estimated light belongs to the variant: it is reloaded with it
        if not self.viewer.set_light(self.viewer.state.light, variant=self.variant.value):
            self._set_quietly(self.variant, self.viewer.state.variant)

    def _upload(self, uploaded) -> None:
        name = Path(uploaded.name).name or "upload.exr"
        folder = Path(self.viewer.uploads.name) / str(len(list(Path(self.viewer.uploads.name).iterdir())))
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / name
        path.write_bytes(uploaded.content)
        label = self.viewer.add_light_file(path)
        if label is None:
            return
        self.light.options = [c.label for c in self.viewer.choices]
        self.light.value = label  # loads it through _light

    def _glb(self) -> None:
        place = self.glb.value
        path = next(p for p in self.viewer.run.glbs if p.name == self.glb_file.value)
        if self.mesh is not None:
            self.mesh.remove()
            self.mesh = None
        if place != "hidden":
            try:
                data = path.read_bytes()
                matrix = dataset_from_glb(path, data)
            except Exception as exc:  # noqa: BLE001 - an unreadable file is one line, the viewer goes on
                self.viewer.tell(f"{path}: cannot be shown ({' '.join(str(exc).split())[:200]})", title="glb")
                self._set_quietly(self.glb, "hidden")
                place = "hidden"
            else:
                self.mesh = self.viewer.server.scene.add_glb(
                    "/glb", data, **dict(zip(("wxyz", "position"), glb_pose(matrix, self._offset(place))))
                )
        self.viewer.update(glb=place)

    def _offset(self, place: str):
        """Beside: to the right of the object as the first camera sees it, one object width and a bit away."""
        if place != "beside":
            return (0.0, 0.0, 0.0)
        _, radius = self.viewer.run.object_frame(self.viewer.state.variant)
        right = self.viewer.start_camera.camtoworld[:3, 0].double().cpu().numpy()
        right[2] = 0.0
        norm = math.hypot(right[0], right[1]) or 1.0
        return tuple(2.4 * radius * right / norm)

    def _snapshot(self, event) -> None:
        if event.client is None:
            return
        try:
            path = self.viewer.snapshot(event.client)
        except (OSError, Exception) as exc:  # noqa: BLE001 - a full disk or a read-only run folder: say so
            self.viewer.tell(f"snapshot not written ({' '.join(str(exc).split())[:200]})", title="snapshot")
            return
        self.viewer.notify(f"matspray view: snapshot {path}")
        event.client.add_notification("snapshot", str(path), auto_close_seconds=6.0)
