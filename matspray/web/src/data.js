// The page's data, written by `matspray.web.pack` as scripts (a page opened from file:// may not fetch files):
// window.MATSPRAY_ASSET = {meta, data} and window.MATSPRAY_LIGHTS = {height, names, data, lut}, each `data` a
// base64 string of deflated little-endian arrays laid out as `meta.arrays` says.

export async function inflate(base64) {
  const bytes = Uint8Array.from(atob(base64), (c) => c.charCodeAt(0));
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate"));
  return new Response(stream).arrayBuffer();
}

const TYPES = { u8: Uint8Array, u16: Uint16Array, i16: Int16Array, f32: Float32Array };

export function views(buffer, arrays) {
  const out = {};
  for (const [name, spec] of Object.entries(arrays)) {
    out[name] = new TYPES[spec.type](buffer, spec.offset, spec.length);
  }
  return out;
}

function srgbToLinear(c) {
  return c <= 0.04045 ? c / 12.92 : ((c + 0.055) / 1.055) ** 2.4;
}

// the quantised splats as the float RGBA textures' contents (`pack.py` says how each field is stored)
export function decodeSplats(meta, a) {
  const n = meta.count;
  const width = meta.textureWidth;
  const texels = width * Math.ceil(n / width) * 4;
  const centre = new Float32Array(texels);
  const rotation = new Float32Array(texels);
  const scale = new Float32Array(texels);
  const base = new Float32Array(texels);
  const normal = new Float32Array(texels);
  const [lo, hi] = [meta.positionMin, meta.positionMax];
  const [slo, shi] = [meta.logScaleMin, meta.logScaleMax];
  const srgb = Float32Array.from({ length: 256 }, (_, i) => srgbToLinear(i / 255));
  for (let i = 0; i < n; i++) {
    const o = 4 * i;
    for (let c = 0; c < 3; c++) {
      centre[o + c] = lo[c] + (a.position[3 * i + c] / 65535) * (hi[c] - lo[c]);
      scale[o + c] = Math.exp(slo + (a.logScale[3 * i + c] / 65535) * (shi - slo));
      base[o + c] = srgb[a.baseColor[3 * i + c]];
      normal[o + c] = Math.max(a.normal[3 * i + c] / 32767, -1);
    }
    centre[o + 3] = a.opacity[i] / 255;
    let len = 0;
    for (let c = 0; c < 4; c++) {
      rotation[o + c] = Math.max(a.rotation[4 * i + c] / 32767, -1);
      len += rotation[o + c] ** 2;
    }
    len = Math.sqrt(len) || 1;
    for (let c = 0; c < 4; c++) rotation[o + c] /= len;
    scale[o + 3] = a.roughness[i] / 255;
    base[o + 3] = a.metallic[i] / 255;
  }
  return { centre, rotation, scale, base, normal, width, height: Math.ceil(n / width) };
}
