// Small vector helpers on plain arrays [x, y, z]. JavaScript numbers are doubles, so
// camera math keeps full precision for models far from the origin.

export const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
export const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
export const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
export const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
export const cross = (a, b) => [
  a[1] * b[2] - a[2] * b[1],
  a[2] * b[0] - a[0] * b[2],
  a[0] * b[1] - a[1] * b[0],
];
export const length = (a) => Math.hypot(a[0], a[1], a[2]);
export const distance = (a, b) => length(sub(a, b));
export const normalize = (a) => {
  const l = length(a);
  return l > 0 ? scale(a, 1 / l) : [0, 0, 0];
};
export const lerp = (a, b, t) => add(a, scale(sub(b, a), t));

// Rotates v about the unit axis by angle (radians), Rodrigues' formula.
export function rotate(v, axis, angle) {
  const c = Math.cos(angle), s = Math.sin(angle);
  return add(add(scale(v, c), scale(cross(axis, v), s)), scale(axis, dot(axis, v) * (1 - c)));
}

export function formatLength(d) {
  if (!Number.isFinite(d)) return "–";
  const a = Math.abs(d);
  if (a !== 0 && (a < 1e-3 || a >= 1e6)) return d.toExponential(3);
  return d.toPrecision(Math.max(4, Math.ceil(Math.log10(a + 1)) + 3));
}
