// The split-sum light of `matspray.render.shade.envmap` in the browser: the same sums over the same pixels, so that
// a light prefiltered here shades as `matspray relight --env-height LIGHT_HEIGHT` shades (the page's light is that
// many rows). Each map is laid out for bilinear lookup as `_padded_rows` lays it out: rows at v = k / 2h (pixel rows
// at odd k, their means between them, the poles' mean radiance at k = 0 and 2h), columns wrapped by one each side.

export const LEVELS = [0.04, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]; // envmap.DEFAULT_LEVELS
const MIN_ROUGHNESS = 0.04;
const PIXELS_PER_LOBE = 2.0;
const MIN_LEVEL_HEIGHT = 16;
const DIFFUSE_HEIGHT = 16;
export const MIN_RADIANCE = 1e-4;

function coarsestHeight(height, atLeast) {
  let h = height;
  while (h % 2 === 0 && h / 2 >= atLeast) h /= 2;
  return h;
}

function levelHeight(roughness, height) {
  const alpha = Math.max(roughness, MIN_ROUGHNESS) ** 2;
  return coarsestHeight(height, Math.max((PIXELS_PER_LOBE * Math.PI) / alpha, MIN_LEVEL_HEIGHT));
}

function levelAlpha(roughness) {
  // float32 as the shading rounds it (`envmap.level_alpha`)
  const r = Math.fround(Math.min(Math.max(roughness, MIN_ROUGHNESS), 1.0));
  return Math.fround(r * r);
}

// the weights between output pixel (a, column 0) and every input pixel: [hOut][hIn][wIn], float64
function lobeWeights(kind, alpha, hIn, hOut) {
  const wIn = 2 * hIn;
  const stride = hIn / hOut;
  const weights = new Float64Array(hOut * hIn * wIn);
  const solid = new Float64Array(hIn);
  for (let b = 0; b < hIn; b++) {
    solid[b] = (Math.cos((b / hIn) * Math.PI) - Math.cos(((b + 1) / hIn) * Math.PI)) * ((2 * Math.PI) / wIn);
  }
  const cosPhi = new Float64Array(wIn);
  for (let m = 0; m < wIn; m++) cosPhi[m] = Math.cos((m + 0.5 - stride / 2) * ((2 * Math.PI) / wIn));
  const a2 = alpha * alpha;
  for (let a = 0; a < hOut; a++) {
    const to = ((a + 0.5) / hOut) * Math.PI;
    let sum = 0;
    for (let b = 0; b < hIn; b++) {
      const ti = ((b + 0.5) / hIn) * Math.PI;
      const cc = Math.cos(to) * Math.cos(ti);
      const ss = Math.sin(to) * Math.sin(ti);
      for (let m = 0; m < wIn; m++) {
        const c = cc + ss * cosPhi[m];
        let w = Math.max(c, 0) * solid[b];
        if (kind === "ggx" && w > 0) {
          const nh = Math.min(Math.sqrt(Math.max((1 + c) / 2, 0)), 1);
          const denom = nh * nh * (a2 - 1) + 1;
          const d = a2 / (Math.PI * denom * denom);
          const nl = Math.max(c, 0);
          const v = 0.5 / Math.max(nl + Math.sqrt(nl * nl * (1 - a2) + a2), 1e-12);
          w *= d * v;
        }
        weights[(a * hIn + b) * wIn + m] = w;
        sum += w;
      }
    }
    const scale = kind === "ggx" ? 1 / sum : Math.PI / sum;
    for (let i = a * hIn * wIn; i < (a + 1) * hIn * wIn; i++) weights[i] *= scale;
  }
  return weights;
}

// out[a, j] = sum_{b, m} w[a, b, m] map[b, stride j + m (wrapped)], padded for lookup: {rows, cols, data RGBA}
function correlatePadded(map, hIn, weights, hOut) {
  const wIn = 2 * hIn;
  const wOut = 2 * hOut;
  const stride = hIn / hOut;
  const out = new Float64Array(hOut * wOut * 3);
  for (let a = 0; a < hOut; a++) {
    for (let b = 0; b < hIn; b++) {
      const row = (a * hIn + b) * wIn;
      for (let m = 0; m < wIn; m++) {
        const w = weights[row + m];
        if (w === 0) continue;
        for (let j = 0; j < wOut; j++) {
          const src = (b * wIn + ((stride * j + m) % wIn)) * 3;
          const dst = (a * wOut + j) * 3;
          out[dst] += w * map[src];
          out[dst + 1] += w * map[src + 1];
          out[dst + 2] += w * map[src + 2];
        }
      }
    }
  }
  const rows = 2 * hOut + 1;
  const cols = wOut + 2;
  const data = new Float32Array(rows * cols * 4);
  const pixel = (a, j, c) => out[(a * wOut + (((j % wOut) + wOut) % wOut)) * 3 + c];
  const mean = (a, c) => {
    let s = 0;
    for (let j = 0; j < wOut; j++) s += pixel(a, j, c);
    return s / wOut;
  };
  for (let k = 0; k < rows; k++) {
    for (let col = 0; col < cols; col++) {
      for (let c = 0; c < 3; c++) {
        let v;
        if (k === 0) v = mean(0, c);
        else if (k === rows - 1) v = mean(hOut - 1, c);
        else if (k % 2 === 1) v = pixel((k - 1) / 2, col - 1, c);
        else v = (pixel(k / 2 - 1, col - 1, c) + pixel(k / 2, col - 1, c)) / 2;
        data[(k * cols + col) * 4 + c] = v;
      }
      data[(k * cols + col) * 4 + 3] = 1;
    }
  }
  return { rows, cols, data };
}

// `envmap.downsample_latlong`: solid-angle weighted averages over adaptive pooling's windows; rgb [h][2h][3]
export function downsampleLatlong(rgb, height, width, outHeight) {
  if (height <= outHeight) return rgb;
  const outWidth = 2 * outHeight;
  const weight = new Float64Array(height);
  for (let b = 0; b < height; b++) {
    weight[b] = (Math.cos((b / height) * Math.PI) - Math.cos(((b + 1) / height) * Math.PI)) * ((2 * Math.PI) / width);
  }
  const out = new Float32Array(outHeight * outWidth * 3);
  for (let a = 0; a < outHeight; a++) {
    const r0 = Math.floor((a * height) / outHeight);
    const r1 = Math.ceil(((a + 1) * height) / outHeight);
    for (let j = 0; j < outWidth; j++) {
      const c0 = Math.floor((j * width) / outWidth);
      const c1 = Math.ceil(((j + 1) * width) / outWidth);
      const sum = [0, 0, 0];
      let total = 0;
      for (let b = r0; b < r1; b++) {
        for (let m = c0; m < c1; m++) {
          const i = (b * width + m) * 3;
          sum[0] += rgb[i] * weight[b];
          sum[1] += rgb[i + 1] * weight[b];
          sum[2] += rgb[i + 2] * weight[b];
          total += weight[b];
        }
      }
      for (let c = 0; c < 3; c++) out[(a * outWidth + j) * 3 + c] = sum[c] / total;
    }
  }
  return out;
}

// every specular level and the irradiance of a lat-long map rgb [h][2h][3] (linear), as padded images
export function prefilter(rgb, height) {
  const map = Float64Array.from(rgb, (v) => Math.max(v, MIN_RADIANCE)); // EnvironmentMap.from_tensor's floor
  const levels = LEVELS.map((r) => {
    const h = levelHeight(r, height);
    return correlatePadded(map, height, lobeWeights("ggx", levelAlpha(r), height, h), h);
  });
  const h = coarsestHeight(height, DIFFUSE_HEIGHT);
  const irradiance = correlatePadded(map, height, lobeWeights("cosine", 0, height, h), h);
  return { levels, irradiance };
}
