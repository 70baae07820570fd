// Plots and labels in µm: round tick values, and the profiles' plot with axes, ticks and units.

// Round values between `low` and `high`, about `count` of them (steps of 1, 2 or 5 times a power
// of ten).
export function niceTicks(low, high, count = 5) {
  if (!(high > low)) return [low];
  const rough = (high - low) / count;
  const power = 10 ** Math.floor(Math.log10(rough));
  const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= rough);
  const ticks = [];
  for (let value = Math.ceil(low / step) * step; value <= high + step * 1e-9; value += step) ticks.push(+value.toPrecision(12));
  return ticks;
}

// A number with `significant` digits ("2.0"), never in exponent form between 1e-6 and 1e21: toPrecision
// writes 120 to two digits as "1.2e+2", which becomes "120".
export function formatNumber(value, significant = 3) {
  if (value === null || value === undefined || !Number.isFinite(value)) return "–";
  const text = value.toPrecision(significant);
  return text.includes("e") ? String(+text) : text;
}

// A measured value with its standard uncertainty and unit, as fractoscope.numbers writes it (the
// report and the command line): the uncertainty with two significant digits, the value to the
// same decimal place ("16.1 ± 1.6 µm"); without an uncertainty, three significant digits.
export function formatMeasured(value, uncertainty, unit) {
  if (value === null || value === undefined || !Number.isFinite(value)) return `n/a ${unit}`;
  if (!(uncertainty > 0) || !Number.isFinite(uncertainty)) return `${formatNumber(value, 3)} ${unit}`;
  const places = decimalsFor(uncertainty);
  return `${plain(value, places)} ± ${plain(uncertainty, places)} ${unit}`;
}

// The decimal places at which `uncertainty` (> 0) shows two significant digits (negative: tens...).
function decimalsFor(uncertainty) {
  let exponent = Math.floor(Math.log10(Math.abs(uncertainty)));
  const rounded = +Math.abs(uncertainty).toPrecision(2);
  exponent = Math.floor(Math.log10(rounded));
  return Math.min(1 - exponent, 12);
}

// `value` rounded to `places` decimals (negative: to tens, hundreds...), without "-0".
function plain(value, places) {
  const text = places >= 0 ? value.toFixed(places) : (Math.round(value / 10 ** -places) * 10 ** -places).toFixed(0);
  return /^-[0.]+$/.test(text) ? text.slice(1) : text;
}

// A length or height in µm with as many decimals as its size asks for.
export function formatUm(value, digits = 3) {
  if (value === null || !Number.isFinite(value)) return "–";
  const magnitude = Math.abs(value);
  const decimals = magnitude >= 100 ? 1 : magnitude >= 10 ? Math.max(digits - 2, 1) : digits;
  return `${value.toFixed(decimals)} µm`;
}

// Draws every profile ({distance_um, z_um, colour, label}) on one canvas: distance along the
// line on x, height on y, both with ticks in µm and grid lines.
export function plotProfiles(canvas, profiles) {
  const ratio = window.devicePixelRatio || 1;
  const width = canvas.clientWidth || canvas.width;
  const height = canvas.clientHeight || canvas.height;
  canvas.width = Math.round(width * ratio);
  canvas.height = Math.round(height * ratio);
  const context = canvas.getContext("2d");
  context.setTransform(ratio, 0, 0, ratio, 0, 0);
  context.clearRect(0, 0, width, height);
  const series = profiles.map((p) => ({ ...p, points: p.distance_um.map((d, i) => [d, p.z_um[i]]).filter(([, z]) => z !== null) }))
    .filter((p) => p.points.length > 1);
  if (!series.length) return;
  const all = series.flatMap((p) => p.points);
  const dMax = Math.max(...series.map((p) => p.distance_um.at(-1)));
  let [zLow, zHigh] = [Math.min(...all.map((p) => p[1])), Math.max(...all.map((p) => p[1]))];
  if (zHigh - zLow < 1e-6) [zLow, zHigh] = [zLow - 0.5, zHigh + 0.5];
  const margin = { left: 44, right: 8, top: 8, bottom: 30 };
  const x = (d) => margin.left + (d / (dMax || 1)) * (width - margin.left - margin.right);
  const y = (z) => height - margin.bottom - ((z - zLow) / (zHigh - zLow)) * (height - margin.top - margin.bottom);
  context.font = "10px system-ui, sans-serif";
  context.strokeStyle = "#ddd";
  context.fillStyle = "#333";
  context.lineWidth = 1;
  context.textAlign = "center";
  context.textBaseline = "top";
  for (const d of niceTicks(0, dMax, 6)) {
    context.beginPath();
    context.moveTo(x(d), margin.top);
    context.lineTo(x(d), height - margin.bottom);
    context.stroke();
    context.fillText(`${+d.toPrecision(4)}`, x(d), height - margin.bottom + 3);
  }
  context.textAlign = "right";
  context.textBaseline = "middle";
  for (const z of niceTicks(zLow, zHigh, 6)) {
    context.beginPath();
    context.moveTo(margin.left, y(z));
    context.lineTo(width - margin.right, y(z));
    context.stroke();
    context.fillText(`${+z.toPrecision(4)}`, margin.left - 4, y(z));
  }
  context.strokeStyle = "#666";
  context.strokeRect(margin.left, margin.top, width - margin.left - margin.right, height - margin.top - margin.bottom);
  context.textAlign = "center";
  context.textBaseline = "bottom";
  context.fillText("distance along the line (µm)", margin.left + (width - margin.left - margin.right) / 2, height - 1);
  context.save();
  context.translate(10, margin.top + (height - margin.top - margin.bottom) / 2);
  context.rotate(-Math.PI / 2);
  context.textBaseline = "middle";
  context.fillText("height (µm)", 0, 0);
  context.restore();
  context.lineWidth = 1.5;
  for (const profile of series) {
    context.strokeStyle = profile.colour;
    context.beginPath();
    let drawing = false;
    profile.distance_um.forEach((d, i) => {
      const z = profile.z_um[i];
      if (z === null) {
        drawing = false;
        return;
      }
      if (drawing) context.lineTo(x(d), y(z));
      else context.moveTo(x(d), y(z));
      drawing = true;
    });
    context.stroke();
  }
}
