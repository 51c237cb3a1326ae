// Legends of the channel view: the colormaps of isosr_server/channels.py, drawn from a frame's
// `legend` ({channel, lo, hi, unit, colormap, stops}), and a coloring's on a shaded frame (with its stops).

/** Hue (direction) and value (length / hi) of a flow vector, as channels.py colors it; rgb in [0, 1]. */
export function flowColor(fx, fy, hi) {
  const hue = ((Math.atan2(fy, fx) / (2 * Math.PI)) % 1 + 1) % 1;
  const value = hi > 0 ? Math.min(Math.hypot(fx, fy) / hi, 1) : 0;
  const k = (n) => (n + hue * 6) % 6;
  const channel = (n) => value * (1 - Math.max(0, Math.min(k(n), 4 - k(n), 1)));
  return [channel(5), channel(3), channel(1)];
}

function interpolate(stops, t) {
  const x = Math.min(Math.max(t, 0), 1) * (stops.length - 1);
  const i = Math.min(Math.floor(x), stops.length - 2);
  const f = x - i;
  return stops[i].map((v, c) => v + (stops[i + 1][c] - v) * f);
}

export function drawLegend(canvas, legend) {
  const g = canvas.getContext("2d");
  const { width: w, height: h } = canvas;
  const pixels = g.createImageData(w, h);
  for (let y = 0; y < h; y++) {
    for (let x = 0; x < w; x++) {
      const t = x / (w - 1);
      let rgb;
      if (legend.stops) rgb = interpolate(legend.stops, t);
      else if (legend.colormap === "normal") {
        // Each legend column: a normal swept from -x to +x, rows from +y to -y, z facing the viewer.
        const nx = 2 * t - 1;
        const ny = 1 - (2 * y) / (h - 1);
        const nz = Math.sqrt(Math.max(0, 1 - nx * nx - ny * ny));
        rgb = [nx * 0.5 + 0.5, ny * 0.5 + 0.5, nz * 0.5 + 0.5];
      } else if (legend.colormap === "flow") {
        // Columns sweep the direction, rows the length (top: hi).
        const angle = t * 2 * Math.PI;
        const length = legend.hi * (1 - y / (h - 1));
        rgb = flowColor(length * Math.cos(angle), length * Math.sin(angle), legend.hi);
      } else rgb = [t, t, t];
      const at = 4 * (y * w + x);
      pixels.data[at] = 255 * rgb[0];
      pixels.data[at + 1] = 255 * rgb[1];
      pixels.data[at + 2] = 255 * rgb[2];
      pixels.data[at + 3] = 255;
    }
  }
  g.putImageData(pixels, 0, 0);
}
