// What tests and benchmarks ask of the page beyond its script interface (frame timing, the shape a frame was drawn
// in, the viewer itself). Installed on window.matspray only when the page is opened with `?test` in its address:
// the tests run the very script that ships (no second build whose code could differ), and a page opened plainly
// offers none of it.

import { prefilter } from "./prefilter.js";

export const TEST_PARAMETER = "test";

export function wantsTestHooks(search) {
  return new URLSearchParams(search).has(TEST_PARAMETER);
}

// milliseconds per frame over `frames` frames, each turned by `step` degrees (sorting included), waiting for each
// to finish (a pixel read back); `moving`: as while the view is dragged (smaller frames), else full size
function timeFrames(viewer, frames, step, moving) {
  const gl = viewer.renderer.getContext();
  const pixel = new Uint8Array(4);
  viewer.moving = moving;
  const start = performance.now();
  for (let i = 0; i < frames; i++) {
    viewer.turn += step;
    viewer.render();
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel);
  }
  const ms = (performance.now() - start) / frames;
  viewer.moving = false;
  return ms;
}

export function installTestHooks(api, viewer) {
  Object.assign(api, {
    viewer,
    timeFrames: (frames, step, moving = false) => timeFrames(viewer, frames, step, moving),
    moving: () => viewer.moving,
    blends: () => viewer.blends, // G-buffers blended so far (a new light or exposure only shades again)
    // [the typical footprint, the last frame's shape]; forceShape("triangles" | "rectangles" | null: by footprint)
    drawnAs: () => [viewer.footprint, viewer.shape.indices === 3 ? "triangles" : "rectangles"],
    forceShape: (shape) => {
      viewer.forcedShape = shape && { triangles: 3, rectangles: 6 }[shape];
      viewer.render();
    },
    // milliseconds to prefilter the current light again (what a dropped file costs besides reading it)
    timePrefilter: () => {
      const light = viewer.lights.entries[viewer.lightIndex];
      const start = performance.now();
      prefilter(light.rgb, light.height);
      return performance.now() - start;
    },
  });
}
