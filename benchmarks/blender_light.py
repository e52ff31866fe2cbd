"""Where Blender shows MatSpray's lat-long light: a check of the light's orientation on import (docs/guide/export.md).

    python -m benchmarks.blender_light        # needs `blender` on PATH (Debian: apt install blender)

Writes a light in MatSpray's lat-long convention (`matspray.render.shade.latlong`) that is black but for a red patch
around direction +x and a green one around +y, sets it as Blender's world (an Environment Texture node, default
vector), renders four views from the origin with Cycles, along +x, -x, +y and -y, and prints each view's mean red and
green. Where the patches land says how Blender's world mapping relates to MatSpray's.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from matspray.render.shade.latlong import pixel_directions

# the views' camera rotations (Euler XYZ, degrees): a Blender camera looks along its local -z; x = 90 turns that to +y
ROTATIONS = {"+x": (90, 0, -90), "-x": (90, 0, 90), "+y": (90, 0, 0), "-y": (90, 0, 180)}

BLENDER_SCRIPT = """
import bpy, math, sys
light, out, turn = sys.argv[sys.argv.index("--") + 1:]
scene = bpy.context.scene
scene.render.engine = "CYCLES"
scene.cycles.samples = 4
scene.cycles.use_denoising = False
scene.render.resolution_x = scene.render.resolution_y = 16
scene.view_settings.view_transform = "Standard"
world = bpy.data.worlds.new("light")
scene.world = world
world.use_nodes = True
texture = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
texture.image = bpy.data.images.load(light)
world.node_tree.links.new(texture.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
if float(turn):  # the guide's fix: a Mapping node turning the texture's vector about z
    coordinates = world.node_tree.nodes.new("ShaderNodeTexCoord")
    mapping = world.node_tree.nodes.new("ShaderNodeMapping")
    mapping.inputs["Rotation"].default_value[2] = math.radians(float(turn))
    world.node_tree.links.new(coordinates.outputs["Generated"], mapping.inputs["Vector"])
    world.node_tree.links.new(mapping.outputs["Vector"], texture.inputs["Vector"])
for thing in list(scene.objects):
    bpy.data.objects.remove(thing)
camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
camera.data.angle = math.radians(40)
scene.collection.objects.link(camera)
scene.camera = camera
for name, degrees in ROTATIONS.items():
    camera.rotation_euler = [math.radians(a) for a in degrees]
    scene.render.filepath = f"{out}/view_{name}.png"
    bpy.ops.render.render(write_still=True)
"""


def patch_light(height: int = 32) -> np.ndarray:  # [H, 2H, 3] uint8: red around +x, green around +y
    directions = pixel_directions(height, 2 * height).numpy()
    light = np.zeros((height, 2 * height, 3), np.uint8)
    light[directions @ np.array([1.0, 0.0, 0.0]) > 0.95, 0] = 255
    light[directions @ np.array([0.0, 1.0, 0.0]) > 0.95, 1] = 255
    return light


def blender_views(blender: str = "blender", turn: float = 0.0) -> dict[str, tuple[float, float]]:
    """Each view's mean (red, green) in 0..255, rendered by Blender under `patch_light`, its vector turned by `turn`
    degrees about z with a Mapping node (0: no Mapping node, the Environment Texture's default vector)."""
    with tempfile.TemporaryDirectory() as folder:
        light = Path(folder) / "light.png"
        Image.fromarray(patch_light()).save(light)
        script = Path(folder) / "render.py"
        script.write_text(f"ROTATIONS = {ROTATIONS!r}\n" + BLENDER_SCRIPT)
        command = [blender, "-b", "--factory-startup", "-P", str(script), "--", str(light), folder, str(turn)]
        done = subprocess.run(command, capture_output=True, text=True, timeout=600)
        if done.returncode != 0:
            raise RuntimeError(f"blender failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
        views = {}
        for name in ROTATIONS:
            image = np.asarray(Image.open(Path(folder) / f"view_{name}.png").convert("RGB"), dtype=np.float64)
            views[name] = (float(image[..., 0].mean()), float(image[..., 1].mean()))
        return views


def main() -> int:
    blender = shutil.which("blender")
    if blender is None:
        print("blender is not on PATH (Debian: apt install blender)", file=sys.stderr)
        return 2
    for turn in (0.0, 180.0):
        views = blender_views(blender, turn)
        setup = "default vector" if not turn else f"Mapping node turning z by {turn:g} degrees"
        for name, (red, green) in views.items():
            print(f"{setup}: Blender's view along {name}: red {red:6.1f}, green {green:6.1f}")
        red_at, green_at = (max(views, key=lambda name: views[name][k]) for k in (0, 1))
        print(f"{setup}: MatSpray's +x shows along {red_at} in Blender, its +y along {green_at}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
