// Splats in drawing order: farthest first by camera-space depth (the order `render.raster` blends in, reversed),
// those behind the near plane left out. A radix sort of the depths' float32 bits (positive floats order as their
// bits do), exact, in four passes of 8 bits: a few milliseconds for 200 000 splats.

const NEAR = 0.01;
let scratch = null;

export function sortBackToFront(centre, count, viewmat, out) {
  if (!scratch || scratch.keys.length < count) {
    scratch = {
      keys: new Uint32Array(count),
      keys2: new Uint32Array(count),
      ids: new Uint32Array(count),
      ids2: new Uint32Array(count),
      depth: new Float32Array(1),
    };
  }
  const { keys, keys2, ids, ids2, depth } = scratch;
  const bits = new Uint32Array(depth.buffer);
  const [r0, r1, r2, tz] = [viewmat[8], viewmat[9], viewmat[10], viewmat[11]];
  let visible = 0;
  for (let i = 0; i < count; i++) {
    const z = r0 * centre[4 * i] + r1 * centre[4 * i + 1] + r2 * centre[4 * i + 2] + tz;
    if (!(z > NEAR)) continue;
    depth[0] = z;
    keys[visible] = bits[0];
    ids[visible] = i;
    visible++;
  }
  let [kIn, kOut, iIn, iOut] = [keys, keys2, ids, ids2];
  const counts = new Uint32Array(256);
  for (let shift = 0; shift < 32; shift += 8) {
    counts.fill(0);
    for (let i = 0; i < visible; i++) counts[(kIn[i] >>> shift) & 255]++;
    let sum = 0;
    for (let b = 255; b >= 0; b--) {
      // descending: the largest depth first
      const c = counts[b];
      counts[b] = sum;
      sum += c;
    }
    for (let i = 0; i < visible; i++) {
      const slot = counts[(kIn[i] >>> shift) & 255]++;
      kOut[slot] = kIn[i];
      iOut[slot] = iIn[i];
    }
    [kIn, kOut, iIn, iOut] = [kOut, kIn, iOut, iIn];
  }
  for (let i = 0; i < visible; i++) out[i] = iIn[i];
  return visible;
}
