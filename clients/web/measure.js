// Measurement tools on the surface: point height, distance, step height between two areas, angle,
// and profiles. Points are picked on the shown tiles; every value comes from the server's data
// (/api/specimens/ID/heights and /profile), not from the level of detail on screen. Lines and
// markers live in `overlay`, a group in the tileset frame (x right, y up the image, z height, m).
import * as THREE from "three";
import { Line2 } from "three/addons/lines/Line2.js";
import { LineGeometry } from "three/addons/lines/LineGeometry.js";
import { LineMaterial } from "three/addons/lines/LineMaterial.js";
import { formatMeasured, formatUm, plotProfiles } from "./plot.js";

const METRES_PER_UM = 1e-6;
const COLOURS = ["#ff3355", "#33c3ff", "#ffd23f", "#b27bff", "#3dff8f", "#ff8c1a"];
export const TOOLS = {
  point: { points: 1, name: "Height", hint: ["click a point"] },
  distance: { points: 2, name: "Distance", hint: ["click the first point", "click the second point"] },
  step: { points: 4, name: "Step", hint: ["area 1: click a corner", "area 1: click the opposite corner", "area 2: click a corner", "area 2: click the opposite corner"] },
  angle: { points: 3, name: "Angle", hint: ["click the first arm's end", "click the vertex", "click the second arm's end"] },
  profile: { points: 2, name: "Profile", hint: ["click where the profile starts", "click where it ends"] },
};

const toTileset = (x_um, y_um, z_um) => new THREE.Vector3(x_um * METRES_PER_UM, -y_um * METRES_PER_UM, z_um * METRES_PER_UM);

export class Measurements {
  // `api(path)` fetches from the server; `specimen()` gives {id, pixelSizeUm} of the open one;
  // `onChange()` is called when the list changes (for the permalink), `redraw()` when the
  // overlay does.
  constructor({ overlay, api, specimen, onChange, redraw, elements }) {
    Object.assign(this, { overlay, api, specimen, onChange, redraw, elements });
    this.items = [];
    this.tool = null;
    this.picked = [];
    this.pending = 0;
    this.lineMaterials = new Set();
  }

  start(tool) {
    this.tool = tool;
    this.picked = [];
    this.clearPickMarkers();
    this.showHint();
  }

  // A point picked on the surface: {x_um, y_um, z_um} (z from the shown mesh, until measured).
  async pick(point) {
    if (!this.tool) return false;
    this.picked.push(point);
    this.pickMarkers = this.pickMarkers ?? [];
    this.pickMarkers.push(this.addMarker(point, COLOURS[this.items.length % COLOURS.length]));
    if (this.picked.length < TOOLS[this.tool].points) {
      this.showHint();
      return true;
    }
    const [tool, points] = [this.tool, this.picked.map(({ x_um, y_um }) => ({ x_um, y_um }))];
    this.tool = null;
    this.picked = [];
    this.clearPickMarkers();
    await this.add(tool, points);
    return true;
  }

  // Measures and draws one measurement of `tool` through `points` ([{x_um, y_um}]).
  async add(tool, points) {
    const item = { tool, points, colour: COLOURS[this.items.length % COLOURS.length], objects: [], index: this.items.length + 1 };
    this.items.push(item);
    this.pending += 1;
    this.showHint();
    try {
      item.result = await this[tool](points);
      item.text = this.describe(item);
      this.draw(item);
    } catch (error) {
      item.text = `${TOOLS[tool].name}: ${error.message}`;
    } finally {
      this.pending -= 1;
      this.showHint();
      this.render();
      this.onChange();
    }
    return item;
  }

  clear() {
    for (const item of this.items) for (const object of item.objects) this.dispose(object);
    this.items = [];
    this.tool = null;
    this.picked = [];
    this.clearPickMarkers();
    window.viewer.profile = null;
    this.showHint();
    this.render();
    this.onChange();
  }

  // The list as text for a permalink ("profile:x,y,x,y;point:x,y", µm) and back.
  encode() {
    return this.items.map((item) => `${item.tool}:${item.points.map((p) => `${+p.x_um.toFixed(3)},${+p.y_um.toFixed(3)}`).join(",")}`).join(";");
  }

  async decode(text) {
    for (const part of (text || "").split(";").filter(Boolean)) {
      const [tool, numbers] = part.split(":");
      const values = (numbers || "").split(",").map(Number);
      if (!TOOLS[tool] || values.length !== 2 * TOOLS[tool].points || !values.every(Number.isFinite)) continue;
      const points = [];
      for (let i = 0; i < values.length; i += 2) points.push({ x_um: values[i], y_um: values[i + 1] });
      await this.add(tool, points);
    }
  }

  async getJson(path) {
    const response = await this.api(`/api/specimens/${this.specimen().id}/${path}`);
    const result = await response.json();
    if (!response.ok) throw new Error(result.error || response.statusText);
    return result;
  }

  // Statistics of the measured heights in a rectangle (x0, y0, x1, y1) µm.
  heights(region) {
    return this.getJson(`heights?region=${region.map((v) => v.toFixed(4)).join(",")}`);
  }

  async heightAt(point) {
    const half = this.specimen().pixelSizeUm / 2;
    const stats = await this.heights([point.x_um - half, point.y_um - half, point.x_um + half, point.y_um + half]);
    if (stats.median_um === null) throw new Error(`nothing measured at (${point.x_um.toFixed(1)}, ${point.y_um.toFixed(1)}) µm`);
    return { ...point, z_um: stats.median_um };
  }

  async point([p]) {
    return { at: await this.heightAt(p) };
  }

  async distance(points) {
    const [a, b] = await Promise.all(points.map((p) => this.heightAt(p)));
    const horizontal = Math.hypot(b.x_um - a.x_um, b.y_um - a.y_um);
    return { at: [a, b], horizontal_um: horizontal, dz_um: b.z_um - a.z_um, distance_um: Math.hypot(horizontal, b.z_um - a.z_um) };
  }

  async step(points) {
    const rectangle = (p, q) => [Math.min(p.x_um, q.x_um), Math.min(p.y_um, q.y_um), Math.max(p.x_um, q.x_um), Math.max(p.y_um, q.y_um)];
    const regions = [rectangle(points[0], points[1]), rectangle(points[2], points[3])];
    const [first, second] = await Promise.all(regions.map((r) => this.heights(r)));
    if (first.mean_um === null || second.mean_um === null) throw new Error("an area holds no measured point");
    const uncertainty = Math.hypot(first.std_um / Math.sqrt(first.count), second.std_um / Math.sqrt(second.count));
    return { regions, areas: [first, second], step_um: second.mean_um - first.mean_um, uncertainty_um: uncertainty };
  }

  async angle(points) {
    const [a, b, c] = await Promise.all(points.map((p) => this.heightAt(p)));
    const arm = (p) => new THREE.Vector3(p.x_um - b.x_um, p.y_um - b.y_um, p.z_um - b.z_um);
    return { at: [a, b, c], angle_deg: THREE.MathUtils.radToDeg(arm(a).angleTo(arm(c))) };
  }

  async profile([start, end]) {
    const result = await this.getJson(`profile?from=${start.x_um},${start.y_um}&to=${end.x_um},${end.y_um}`);
    window.viewer.profile = result;
    return { ...result, start, end };
  }

  describe(item) {
    const r = item.result;
    const label = `${TOOLS[item.tool].name} ${item.index}`;
    switch (item.tool) {
      case "point":
        return `${label}: z = ${formatUm(r.at.z_um)} at (${r.at.x_um.toFixed(1)}, ${r.at.y_um.toFixed(1)}) µm`;
      case "distance":
        return `${label}: ${formatUm(r.distance_um)} (horizontal ${formatUm(r.horizontal_um)}, Δz ${formatUm(r.dz_um)})`;
      case "step":
        return `${label}: ${formatMeasured(r.step_um, r.uncertainty_um, "µm")} (area means ${formatUm(r.areas[0].mean_um)}, ${formatUm(r.areas[1].mean_um)})`;
      case "angle":
        return `${label}: ${r.angle_deg.toFixed(1)}°`;
      default: {
        const p = r.parameters;
        const length = Math.hypot(r.end.x_um - r.start.x_um, r.end.y_um - r.start.y_um);
        // Ra, Rq and Rz are the roughness profile's, after the ISO 21920-3 filters: their cut-offs say what.
        const cutoffs = r.chain ? ` (roughness profile, λs ${formatUm(r.chain.s_filter_um)}, λc ${formatUm(r.chain.l_filter_um)})` : "";
        return `${label}: ${formatUm(length)} long` + (p ? `, Ra ${formatUm(p.Ra)}, Rq ${formatUm(p.Rq)}, Rz ${formatUm(p.Rz)}${cutoffs}` : ", no heights along it");
      }
    }
  }

  draw(item) {
    const r = item.result;
    const add = (object) => {
      item.objects.push(object);
      this.overlay.add(object);
      this.redraw();
    };
    if (item.tool === "profile") {
      // The sampled heights, on the surface: a new geometry for every line.
      let run = [];
      const flush = () => {
        if (run.length > 1) add(this.line(run, item.colour));
        run = [];
      };
      const [dx, dy] = [r.end.x_um - r.start.x_um, r.end.y_um - r.start.y_um];
      const length = Math.hypot(dx, dy) || 1;
      r.distance_um.forEach((d, i) => {
        const z = r.z_um[i];
        if (z === null) flush();
        else run.push(toTileset(r.start.x_um + (dx * d) / length, r.start.y_um + (dy * d) / length, z));
      });
      flush();
      return;
    }
    if (item.tool === "step") {
      r.regions.forEach(([x0, y0, x1, y1], k) => {
        const z = r.areas[k].mean_um;
        add(this.line([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]].map(([x, y]) => toTileset(x, y, z)), item.colour));
      });
      return;
    }
    const points = (Array.isArray(r.at) ? r.at : [r.at]).map((p) => toTileset(p.x_um, p.y_um, p.z_um));
    for (const point of points) add(this.marker(point, item.colour));
    if (points.length > 1) add(this.line(points, item.colour));
  }

  line(points, colour) {
    const geometry = new LineGeometry();
    geometry.setPositions(points.flatMap((p) => [p.x, p.y, p.z]));
    const material = new LineMaterial({ color: colour, linewidth: 3, depthTest: false, transparent: true });
    material.resolution.copy(this.resolution ?? new THREE.Vector2(1, 1));
    this.lineMaterials.add(material);
    const line = new Line2(geometry, material);
    line.computeLineDistances();
    line.renderOrder = 10;
    return line;
  }

  marker(position, colour) {
    const geometry = new THREE.BufferGeometry().setFromPoints([position]);
    const points = new THREE.Points(geometry, new THREE.PointsMaterial({ color: colour, size: 12, sizeAttenuation: false, depthTest: false }));
    points.renderOrder = 11;
    return points;
  }

  addMarker(point, colour) {
    const marker = this.marker(toTileset(point.x_um, point.y_um, point.z_um), colour);
    this.overlay.add(marker);
    this.redraw();
    return marker;
  }

  clearPickMarkers() {
    for (const marker of this.pickMarkers ?? []) this.dispose(marker);
    this.pickMarkers = [];
  }

  dispose(object) {
    this.redraw();
    this.overlay.remove(object);
    object.geometry.dispose();
    this.lineMaterials.delete(object.material);
    object.material.dispose();
  }

  setResolution(width, height) {
    this.resolution = new THREE.Vector2(width, height);
    for (const material of this.lineMaterials) material.resolution.copy(this.resolution);
  }

  showHint() {
    const hint = this.elements.hint;
    hint.classList.toggle("busy", this.pending > 0);
    document.querySelectorAll("[data-tool]").forEach((button) => button.classList.toggle("active", button.dataset.tool === this.tool));
    if (this.tool) hint.textContent = `${TOOLS[this.tool].name}: ${TOOLS[this.tool].hint[this.picked.length]}`;
    else hint.textContent = this.pending ? "measuring" : "";
  }

  render() {
    const list = this.elements.list;
    list.replaceChildren(...this.items.map((item) => {
      const entry = document.createElement("li");
      const swatch = document.createElement("span");
      swatch.className = "swatch";
      swatch.style.background = item.colour;
      entry.append(swatch, item.text ?? `${TOOLS[item.tool].name} ${item.index}: measuring`);
      return entry;
    }));
    const profiles = this.items.filter((item) => item.tool === "profile" && item.result);
    this.elements.plot.hidden = !profiles.length;
    plotProfiles(this.elements.plot, profiles.map((item) => ({ ...item.result, colour: item.colour })));
  }
}
