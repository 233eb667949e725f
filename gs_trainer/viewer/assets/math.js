// Small vector and pose helpers of the gaps viewer. Poses are in the project's convention (OpenCV axes: x right,
// y down, z forward): R is the world-to-camera rotation as 9 numbers, row-major, t the translation, so that
// x_cam = R x_world + t and the camera centre is -R^T t.
'use strict';

const GapsMath = (() => {
  const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (a) => Math.sqrt(dot(a, a));
  const normalize = (a) => {
    const n = norm(a);
    return n > 0 ? scale(a, 1 / n) : [0, 0, 0];
  };

  // Row i of a row-major 3x3 matrix.
  const row = (R, i) => [R[3 * i], R[3 * i + 1], R[3 * i + 2]];
  const mulVec = (R, v) => [dot(row(R, 0), v), dot(row(R, 1), v), dot(row(R, 2), v)];
  const mulTransposedVec = (R, v) => [
    R[0] * v[0] + R[3] * v[1] + R[6] * v[2],
    R[1] * v[0] + R[4] * v[1] + R[7] * v[2],
    R[2] * v[0] + R[5] * v[1] + R[8] * v[2],
  ];
  const mul = (A, B) => {
    const C = new Array(9);
    for (let i = 0; i < 3; ++i)
      for (let j = 0; j < 3; ++j) C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
    return C;
  };
  const transpose = (R) => [R[0], R[3], R[6], R[1], R[4], R[7], R[2], R[5], R[8]];

  // Rotation by `angle` (radians) about the unit axis (Rodrigues).
  const axisAngle = (axis, angle) => {
    const [x, y, z] = normalize(axis);
    const c = Math.cos(angle), s = Math.sin(angle), k = 1 - c;
    return [
      c + x * x * k, x * y * k - z * s, x * z * k + y * s,
      y * x * k + z * s, c + y * y * k, y * z * k - x * s,
      z * x * k - y * s, z * y * k + x * s, c + z * z * k,
    ];
  };

  // The pose (R, t) of a camera at `centre` with rotation R.
  const translationOf = (R, centre) => scale(mulVec(R, centre), -1);
  const centreOf = (R, t) => scale(mulTransposedVec(R, t), -1);

  // Re-orthonormalises R (rows right, down, forward) after many small rotations.
  const orthonormalize = (R) => {
    const f = normalize(row(R, 2));
    const r = normalize(cross(row(R, 1), f));
    const d = cross(f, r);
    return [...r, ...d, ...f];
  };

  // A rotation looking along `forward` with `up` (world) pointing up in the image.
  const lookRotation = (forward, up) => {
    const f = normalize(forward);
    let r = cross(f, up);
    if (norm(r) < 1e-9) r = cross(f, Math.abs(f[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0]);
    r = normalize(r);
    const d = cross(f, r);
    return [...r, ...d, ...f];
  };

  const median = (values) => {
    if (values.length === 0) return 0;
    const sorted = Float64Array.from(values).sort();
    return sorted[sorted.length >> 1];
  };

  // The column-major 4x4 clip-space matrix of a pinhole view (world -> clip) for WebGL's line pass:
  // x_ndc = 2 u / W - 1 and y_ndc = 1 - 2 v / H at the pixel (u, v) = (fx x / z + cx, fy y / z + cy).
  const clipMatrix = (view, near, far) => {
    const {width: W, height: H, fx, fy, cx, cy} = view;
    const P = [
      [2 * fx / W, 0, 2 * cx / W - 1, 0],
      [0, -2 * fy / H, 1 - 2 * cy / H, 0],
      [0, 0, (far + near) / (far - near), -2 * far * near / (far - near)],
      [0, 0, 1, 0],
    ];
    const V = [
      [view.R[0], view.R[1], view.R[2], view.t[0]],
      [view.R[3], view.R[4], view.R[5], view.t[1]],
      [view.R[6], view.R[7], view.R[8], view.t[2]],
      [0, 0, 0, 1],
    ];
    const out = new Float32Array(16);
    for (let i = 0; i < 4; ++i)
      for (let j = 0; j < 4; ++j) {
        let s = 0;
        for (let k = 0; k < 4; ++k) s += P[i][k] * V[k][j];
        out[4 * j + i] = s;
      }
    return out;
  };

  return {add, sub, scale, dot, cross, norm, normalize, row, mulVec, mulTransposedVec, mul, transpose, axisAngle,
          translationOf, centreOf, orthonormalize, lookRotation, median, clipMatrix};
})();
