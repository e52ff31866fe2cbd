// `matspray export --web DIR`: the asset relit in the browser on three.js (WebGL 2), as `matspray relight` renders
// it: the Gaussians' materials and normals blended into a G-buffer, each pixel shaded by split-sum image-based
// lighting (shaders.js); the light is prefiltered on the page (prefilter.js), so that a dropped .hdr / .exr lights the
// asset as a packaged one does. window.matspray is the page's interface for scripts: ready, error, lights(),
// setLight, setTurn, setExposure, setCamera (hooks.js adds the tests' hooks when the page's address asks for them).

import * as THREE from "three";
import { EXRLoader } from "three/addons/loaders/EXRLoader.js";
import { HDRLoader } from "three/addons/loaders/HDRLoader.js";
import { decodeSplats, inflate, views } from "./data.js";
import { downsampleLatlong, LEVELS, prefilter } from "./prefilter.js";
import {
  ENLARGE_FRAGMENT,
  PROJECT_FRAGMENT,
  SCREEN_VERTEX,
  SPLAT_FRAGMENT,
  splatVertex,
  shadeFragment,
} from "./shaders.js";
import { sortBackToFront } from "./sort.js";
import { orbitCamera } from "./orbit.js";
import { installTestHooks, wantsTestHooks } from "./hooks.js";

const BACKGROUND = [0.02, 0.02, 0.02]; // linear
// while the view is dragged, the splats are blended at 1 / PREVIEW of the canvas's width and height (the splat pass's
// fragments are nearly all of a frame's time in software WebGL); the frame drawn when the view stops is full size
const PREVIEW = 2;
// a frame whose typical Gaussian's rectangle covers fewer blended pixels than this draws each Gaussian in one
// triangle, else in a rectangle (two): on SwiftShader triangles were faster at 300, rectangles at 750 (docs/dev/web.md)
const TRIANGLE_FOOTPRINT = 500;
const SAMPLES = 256; // Gaussians whose footprints give the typical one
// the alpha below which a Gaussian blends nothing: render.raster's 1/255 in the frame drawn when the view stops; while
// it moves, a higher one, which shrinks each footprint's shape to fewer fragments (docs/dev/web.md)
const CUTOFF = 1 / 255;
const PREVIEW_CUTOFF = 1 / 32;

function floatTexture(data, width, height) {
  const texture = new THREE.DataTexture(data, width, height, THREE.RGBAFormat, THREE.FloatType);
  texture.minFilter = texture.magFilter = THREE.NearestFilter;
  texture.generateMipmaps = false;
  texture.needsUpdate = true;
  return texture;
}

function rawMaterial(vertexShader, fragmentShader, uniforms) {
  return new THREE.RawShaderMaterial({
    glslVersion: THREE.GLSL3,
    vertexShader,
    fragmentShader,
    uniforms,
    depthTest: false,
    depthWrite: false,
  });
}

// a triangle over the whole viewport, for the passes that run once per texel
const SCREEN = new THREE.BufferGeometry();
SCREEN.setAttribute("position", new THREE.BufferAttribute(new Float32Array([-1, -1, 0, 3, -1, 0, -1, 3, 0]), 3));

function sceneOf(geometry, material) {
  const mesh = new THREE.Mesh(geometry, material);
  mesh.frustumCulled = false;
  const scene = new THREE.Scene();
  scene.add(mesh);
  return scene;
}

// the padded maps of prefilter() stacked into one texture: {texture, places [first row, rows, columns] per map}
function lightTexture(filtered) {
  const maps = [...filtered.levels, filtered.irradiance];
  const width = Math.max(...maps.map((m) => m.cols));
  const height = maps.reduce((sum, m) => sum + m.rows, 0);
  const data = new Float32Array(width * height * 4);
  const places = [];
  let row = 0;
  for (const m of maps) {
    for (let k = 0; k < m.rows; k++) data.set(m.data.subarray(k * m.cols * 4, (k + 1) * m.cols * 4), (row + k) * width * 4);
    places.push(new THREE.Vector3(row, m.rows, m.cols));
    row += m.rows;
  }
  return { texture: floatTexture(data, width, height), places };
}

class Viewer {
  constructor(canvas, asset, lights) {
    this.canvas = canvas;
    this.meta = asset.meta;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true, alpha: false });
    this.renderer.setPixelRatio(1);
    this.renderer.autoClear = false;
    // blending into float32 is SwiftShader's fast path (half floats are converted per fragment: 2-3 times slower);
    // it needs EXT_float_blend, which a browser may lack
    const floatBlend = this.renderer.getContext().getExtension("EXT_float_blend");
    this.blendType = floatBlend ? THREE.FloatType : THREE.HalfFloatType;
    this.lights = lights;
    this.camera = new THREE.Camera(); // the shaders project themselves
    this.turn = 0;
    this.exposure = 0;
    this.explicit = null; // a camera given by a script: {viewmat, K, width, height}
    this.moving = false; // drawn at 1 / PREVIEW size while true
    this.targets = {}; // the blend targets by their shrink factor
    this.blends = 0; // G-buffers blended so far (a new light or exposure blends none)
    this.makeSplats(asset.splats);
    this.makeShading();
    this.resize(this.meta.view.width, this.meta.view.height);
  }

  makeSplats(s) {
    // a rectangle (two triangles from four vertices) or a triangle a Gaussian (the vertex shader finds its Gaussian
    // and corner)
    const rectangles = new Uint32Array(6 * this.meta.count);
    for (let k = 0; k < this.meta.count; k++) rectangles.set([4 * k, 4 * k + 1, 4 * k + 2, 4 * k, 4 * k + 2, 4 * k + 3], 6 * k);
    const triangles = new Uint32Array(3 * this.meta.count).map((_, k) => k);
    this.shapes = [6, 3].map((indices) => ({ indices, geometry: new THREE.BufferGeometry() }));
    this.shapes[0].geometry.setIndex(new THREE.BufferAttribute(rectangles, 1));
    this.shapes[1].geometry.setIndex(new THREE.BufferAttribute(triangles, 1));
    // the product of each sampled Gaussian's two largest scales
    this.sampled = Array.from({ length: Math.min(SAMPLES, this.meta.count) }, (_, j) => {
      const i = Math.floor((j * this.meta.count) / Math.min(SAMPLES, this.meta.count));
      const [a, b] = [0, 1, 2].map((k) => s.scale[4 * i + k]).sort((x, y) => y - x);
      return { i, area: a * b };
    });
    this.order = new THREE.DataTexture(new Float32Array(s.width * s.height), s.width, s.height, THREE.RedFormat, THREE.FloatType);
    this.order.minFilter = this.order.magFilter = THREE.NearestFilter;
    this.order.generateMipmaps = false;
    this.means = s.centre;
    // each Gaussian's footprint (PROJECT_FRAGMENT's three outputs), laid out as the splat textures
    this.projectTarget = new THREE.WebGLRenderTarget(s.width, s.height, {
      count: 2,
      type: THREE.FloatType,
      format: THREE.RGBAFormat,
      minFilter: THREE.NearestFilter,
      magFilter: THREE.NearestFilter,
      depthBuffer: false,
    });
    const [centreAxis, extent] = this.projectTarget.textures;
    this.splatUniforms = {
      tCentreAxis: { value: centreAxis },
      tExtent: { value: extent },
      tCentre: { value: floatTexture(s.centre, s.width, s.height) },
      tRotation: { value: floatTexture(s.rotation, s.width, s.height) },
      tScale: { value: floatTexture(s.scale, s.width, s.height) },
      tBase: { value: floatTexture(s.base, s.width, s.height) },
      tNormal: { value: floatTexture(s.normal, s.width, s.height) },
      tOrder: { value: this.order },
      texWidth: { value: s.width },
      viewRotation: { value: new THREE.Matrix3() },
      viewTranslation: { value: new THREE.Vector3() },
      intrinsics: { value: new THREE.Vector4() },
      size: { value: new THREE.Vector2() },
      cutoff: { value: CUTOFF },
      eye: { value: new THREE.Vector3() },
    };
    for (const shape of this.shapes) {
      const material = rawMaterial(splatVertex(shape.indices === 6 ? 4 : 3), SPLAT_FRAGMENT, this.splatUniforms);
      this.blendSplats(material);
      shape.scene = sceneOf(shape.geometry, material);
    }
    this.projectScene = sceneOf(SCREEN, rawMaterial(SCREEN_VERTEX, PROJECT_FRAGMENT, this.splatUniforms));
  }

  blendSplats(material) {
    material.transparent = true;
    material.side = THREE.DoubleSide; // the rectangles turn clockwise on screen: image rows run down
    material.blending = THREE.CustomBlending;
    material.blendEquation = material.blendEquationAlpha = THREE.AddEquation;
    material.blendSrc = material.blendSrcAlpha = THREE.OneFactor;
    material.blendDst = material.blendDstAlpha = THREE.OneMinusSrcAlphaFactor;
  }

  // the median footprint of the sampled Gaussians in canvas pixels (the rectangle's area, as if each faced the
  // camera): 4 (2 ln 255) fx fy s1 s2 / z^2
  typicalFootprint(viewmat, K) {
    const [r0, r1, r2, tz] = [viewmat[8], viewmat[9], viewmat[10], viewmat[11]];
    const areas = this.sampled.map(({ i, area }) => {
      const z = r0 * this.means[4 * i] + r1 * this.means[4 * i + 1] + r2 * this.means[4 * i + 2] + tz;
      return z > 0.01 ? (4 * 2 * Math.log(255) * K[0] * K[1] * area) / (z * z) : 0;
    });
    return areas.sort((x, y) => x - y)[areas.length >> 1];
  }

  makeShading() {
    const u = this.splatUniforms;
    this.shadeUniforms = {
      tBlendedBase: { value: null },
      tBlendedNormal: { value: null },
      tBlendedMaterial: { value: null },
      size: u.size,
      intrinsics: u.intrinsics,
      viewRotation: u.viewRotation,
      background: { value: new THREE.Vector3(...BACKGROUND) },
      tLut: { value: floatTexture(this.lights.lut, 32, 32) },
      tLight: { value: null },
      levelPlace: { value: [] },
      levelRoughness: { value: LEVELS },
      exposure: { value: 1 },
    };
    this.shadeScene = sceneOf(SCREEN, rawMaterial(SCREEN_VERTEX, shadeFragment(LEVELS.length), this.shadeUniforms));
    this.enlargeUniforms = { tShaded: { value: null }, shrink: { value: 1 } };
    this.enlargeScene = sceneOf(SCREEN, rawMaterial(SCREEN_VERTEX, ENLARGE_FRAGMENT, this.enlargeUniforms));
  }

  // the canvas at width x height and the blend targets (the G-buffer) at 1 / shrink of it
  resize(width, height, shrink) {
    if (this.width !== width || this.height !== height) {
      this.renderer.setSize(width, height, false);
      this.canvas.style.width = `${width}px`;
      this.canvas.style.height = `${height}px`;
      Object.values(this.targets).forEach((target) => [target, target.shaded].forEach((t) => t?.dispose()));
      this.targets = {};
      [this.width, this.height] = [width, height];
    }
    if (!this.targets[shrink]) {
      this.targets[shrink] = new THREE.WebGLRenderTarget(Math.ceil(width / shrink), Math.ceil(height / shrink), {
        count: 3,
        type: this.blendType,
        format: THREE.RGBAFormat,
        minFilter: THREE.NearestFilter,
        magFilter: THREE.NearestFilter,
        depthBuffer: false,
      });
      if (shrink > 1) {
        // the frame shaded at the blended size, 8 bits as the canvas holds it: enlarged, the same bytes
        this.targets[shrink].shaded = new THREE.WebGLRenderTarget(Math.ceil(width / shrink), Math.ceil(height / shrink), {
          minFilter: THREE.NearestFilter,
          magFilter: THREE.NearestFilter,
          depthBuffer: false,
        });
      }
    }
    this.target = this.targets[shrink];
    const [base, normal, material] = this.target.textures;
    this.shadeUniforms.tBlendedBase.value = base;
    this.shadeUniforms.tBlendedNormal.value = normal;
    this.shadeUniforms.tBlendedMaterial.value = material;
    this.enlargeUniforms.shrink.value = shrink;
  }

  setLight(index) {
    const light = this.lights.entries[index];
    if (!light.filtered) light.filtered = lightTexture(prefilter(light.rgb, light.height));
    this.shadeUniforms.tLight.value = light.filtered.texture;
    this.shadeUniforms.levelPlace.value = light.filtered.places;
    this.lightIndex = index;
  }

  // {viewmat [16] row-major world-to-camera (OpenCV axes), K [fx, fy, cx, cy], width, height}
  currentCamera() {
    if (this.explicit) return this.explicit;
    const { width, height } = this.meta.view;
    return orbitCamera(this.meta.view, this.turn, width, height);
  }

  render() {
    const cam = this.currentCamera();
    const shrink = this.moving ? PREVIEW : 1;
    this.resize(cam.width, cam.height, shrink);
    const v = cam.viewmat;
    const u = this.splatUniforms;
    u.viewRotation.value.set(v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]);
    u.viewTranslation.value.set(v[3], v[7], v[11]);
    // a blended pixel covers shrink x shrink of the canvas's: its centre projects to (canvas pixel) / shrink
    u.intrinsics.value.set(...cam.K.map((k) => k / shrink));
    u.size.value.set(this.target.width, this.target.height);
    u.cutoff.value = this.moving ? PREVIEW_CUTOFF : CUTOFF;
    // the eye: -R^T t
    const eye = [0, 1, 2].map((c) => -(v[c] * v[3] + v[4 + c] * v[7] + v[8 + c] * v[11]));
    u.eye.value.set(...eye);
    this.shadeUniforms.exposure.value = 2 ** this.exposure;
    const key = v.join(",");
    // a new light or exposure shades the G-buffer of the same view again: only a new view blends the splats
    const blendedKey = [key, cam.K.join(","), cam.width, cam.height, shrink, this.forcedShape].join(";");
    if (blendedKey !== this.blendedFor) {
      this.splat(v, cam.K, key, shrink);
      this.blendedFor = blendedKey;
      this.blends += 1;
    }
    this.shade();
  }

  // each blended pixel shaded once, onto the canvas, or while the view moves onto a target of the blended size that
  // is then enlarged onto it (shading per canvas pixel did the same work for each of a block's pixels)
  shade() {
    const shaded = this.target.shaded;
    this.renderer.setRenderTarget(shaded ?? null);
    this.renderer.render(this.shadeScene, this.camera);
    if (!shaded) return;
    this.enlargeUniforms.tShaded.value = shaded.texture;
    this.renderer.setRenderTarget(null);
    this.renderer.render(this.enlargeScene, this.camera);
  }

  // the G-buffer of the view: the Gaussians sorted (when the view changed), projected and blended
  splat(v, K, key, shrink) {
    const u = this.splatUniforms;
    if (key !== this.sortedFor) {
      // the order changes only when the view does (not with the light or the exposure)
      const visible = sortBackToFront(this.means, this.meta.count, v, this.order.image.data);
      for (const shape of this.shapes) shape.geometry.setDrawRange(0, shape.indices * visible);
      this.footprint = this.typicalFootprint(v, K);
      this.order.needsUpdate = true;
      this.sortedFor = key;
    }
    this.renderer.setClearColor(0x000000, 0);
    this.renderer.setRenderTarget(this.projectTarget);
    this.renderer.render(this.projectScene, this.camera);
    this.renderer.setRenderTarget(this.target);
    this.renderer.clear(true, false, false);
    // the footprint's shape reaches 2 ln(1 / cutoff) variances each way, the typical footprint's 2 ln 255
    const blended = (this.footprint * Math.log(u.cutoff.value)) / Math.log(CUTOFF) / (shrink * shrink);
    const small = blended < TRIANGLE_FOOTPRINT;
    this.shape = this.shapes[(this.forcedShape ?? (small ? 3 : 6)) === 3 ? 1 : 0];
    this.renderer.render(this.shape.scene, this.camera);
  }
}

// a dropped or chosen .hdr / .exr as a light of LIGHT_HEIGHT rows, or a one-line reason it is not one
function parseLightFile(name, buffer, height) {
  const lower = name.toLowerCase();
  let parsed;
  let flip = false;
  if (lower.endsWith(".exr")) {
    parsed = new EXRLoader().setDataType(THREE.FloatType).parse(buffer);
    flip = true; // EXRLoader writes rows bottom up
  } else if (lower.endsWith(".hdr")) {
    parsed = new HDRLoader().setDataType(THREE.FloatType).parse(buffer);
  } else {
    throw new Error(`${name}: not an .hdr or .exr file`);
  }
  const { width, height: rows, data } = parsed;
  if (width !== 2 * rows) throw new Error(`${name}: ${width} x ${rows} is not a lat-long map (width = 2 x height)`);
  const channels = data.length / (width * rows);
  const rgb = new Float32Array(width * rows * 3);
  for (let y = 0; y < rows; y++) {
    const src = flip ? rows - 1 - y : y;
    for (let x = 0; x < width; x++) {
      for (let c = 0; c < 3; c++) {
        const value = data[(src * width + x) * channels + Math.min(c, channels - 1)];
        if (!Number.isFinite(value)) throw new Error(`${name}: holds NaN or Inf values`);
        rgb[(y * width + x) * 3 + c] = Math.max(value, 0);
      }
    }
  }
  return downsampleLatlong(rgb, rows, width, height);
}

async function start() {
  const status = document.getElementById("status");
  const api = (window.matspray = { ready: false, error: null });
  try {
    const asset = window.MATSPRAY_ASSET;
    const lightData = window.MATSPRAY_LIGHTS;
    const assetArrays = views(await inflate(asset.data), asset.meta.arrays);
    const lightArrays = views(await inflate(lightData.data), lightData.arrays);
    const height = lightData.height;
    const lights = {
      lut: lightArrays.lut,
      entries: lightData.names.map((name, i) => ({ name, height: lightData.heights[i], rgb: lightArrays[name] })),
    };
    const viewer = new Viewer(document.getElementById("view"), { meta: asset.meta, splats: decodeSplats(asset.meta, assetArrays) }, lights);
    const select = document.getElementById("light");
    const addOption = (name) => select.add(new Option(name, String(select.options.length)));
    lights.entries.forEach((entry) => addOption(entry.name));
    const draw = (moving = false) => {
      viewer.moving = moving;
      requestAnimationFrame(() => viewer.render());
    };
    const useLight = (index) => {
      viewer.setLight(index);
      select.value = String(index);
      viewer.render();
    };
    select.onchange = () => useLight(Number(select.value));
    const turn = document.getElementById("turn");
    turn.oninput = () => {
      viewer.turn = Number(turn.value);
      viewer.explicit = null;
      draw(true);
    };
    turn.onchange = () => draw(); // let go: full size
    const exposure = document.getElementById("exposure");
    exposure.oninput = () => {
      viewer.exposure = Number(exposure.value);
      draw();
    };
    const addFile = async (file) => {
      try {
        const rgb = parseLightFile(file.name, await file.arrayBuffer(), height);
        lights.entries.push({ name: file.name, height, rgb });
        addOption(file.name);
        useLight(lights.entries.length - 1);
        status.textContent = `lit by ${file.name}`;
      } catch (error) {
        status.textContent = String(error.message || error);
        api.error = status.textContent;
      }
    };
    document.getElementById("file").onchange = (event) => event.target.files[0] && addFile(event.target.files[0]);
    document.body.addEventListener("dragover", (event) => event.preventDefault());
    document.body.addEventListener("drop", (event) => {
      event.preventDefault();
      if (event.dataTransfer.files.length) addFile(event.dataTransfer.files[0]);
    });
    let dragging = null;
    viewer.canvas.addEventListener("pointerdown", (event) => (dragging = event.clientX));
    window.addEventListener("pointerup", () => {
      if (dragging !== null) draw(); // let go: full size
      dragging = null;
    });
    window.addEventListener("pointermove", (event) => {
      if (dragging === null) return;
      viewer.turn = ((viewer.turn + (event.clientX - dragging) * 0.5 + 540) % 360) - 180;
      dragging = event.clientX;
      turn.value = String(viewer.turn);
      viewer.explicit = null;
      draw(true);
    });
    useLight(0);
    Object.assign(api, {
      lights: () => lights.entries.map((e) => e.name),
      setLight: (name) => useLight(lights.entries.findIndex((e) => e.name === name)),
      setCamera: (viewmat, K, width, height) => {
        viewer.explicit = { viewmat, K, width, height };
        viewer.moving = false;
        viewer.render();
      },
      // the controls show what a script set, as they show what the user set
      setTurn: (degrees) => {
        viewer.explicit = null;
        viewer.turn = degrees;
        turn.value = String(degrees);
        viewer.moving = false;
        viewer.render();
      },
      setExposure: (stops) => {
        viewer.exposure = stops;
        exposure.value = String(stops);
        viewer.render();
      },
    });
    if (wantsTestHooks(window.location.search)) installTestHooks(api, viewer);
    api.ready = true;
    const { count, drawnOf } = asset.meta;
    // the Gaussians left out at export add least to the page's frames (matspray/web/detail.py)
    status.textContent = drawnOf > count ? `${count} of the asset's ${drawnOf} Gaussians` : `${count} Gaussians`;
  } catch (error) {
    api.error = String(error && error.stack ? error.stack : error);
    status.textContent = `could not start: ${error.message || error}`;
  }
}

start();
