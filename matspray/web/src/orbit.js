// The page's camera: `matspray relight --views orbit`'s circle (`method.relight.orbit_cameras`), turned by
// `turn` degrees from its first frame, looking at the centre with `Camera.look_at`'s axes (OpenCV: x right,
// y down, z forward).

const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const unit = (a) => {
  const n = Math.hypot(...a);
  return a.map((x) => x / n);
};

export function orbitCamera(view, turn, width, height) {
  const az = (turn * Math.PI) / 180;
  const el = view.elevation;
  const dir = [0, 1, 2].map(
    (c) => Math.cos(el) * (Math.cos(az) * view.first[c] + Math.sin(az) * view.second[c]) + Math.sin(el) * view.up[c],
  );
  const eye = view.center.map((x, c) => x + view.distance * dir[c]);
  const forward = unit(view.center.map((x, c) => x - eye[c]));
  let right = cross(forward, view.up);
  if (Math.hypot(...right) < 1e-9) right = cross(forward, [1, 0, 0]);
  right = unit(right);
  const down = cross(forward, right);
  const rows = [right, down, forward];
  const viewmat = [];
  for (const r of rows) viewmat.push(r[0], r[1], r[2], -(r[0] * eye[0] + r[1] * eye[1] + r[2] * eye[2]));
  viewmat.push(0, 0, 0, 1);
  const scale = width / view.width; // the run's focal length, for the canvas' size
  const K = [view.fx * scale, view.fy * scale, width / 2, height / 2];
  return { viewmat, K, width, height };
}
