// Fractoscope web viewer: streams a specimen's 3D Tiles with 3DTilesRendererJS, draws them lit and
// coloured by the SEM image or by height (surface.js), measures on the surface (measure.js) and
// the roughness of the view, and keeps its state in a permalink.
// Tileset frame (3D Tiles, Z up, metres): x = specimen x, y = -specimen y, z = height.
import * as THREE from "three";
import { MeshoptDecoder } from "three/addons/libs/meshopt_decoder.module.js";
import { TilesRenderer } from "3d-tiles-renderer";
import { GLTFExtensionsPlugin } from "3d-tiles-renderer/plugins";
import { VIEWS, ViewCamera } from "./camera.js";
import { Measurements } from "./measure.js";
import { formatMeasured, formatNumber, formatUm, niceTicks } from "./plot.js";
import { SpecimenList, isUnderWay } from "./specimens.js";
import { MAX_ROIS, RAMP, isWallMesh, lightDirection, rampGradient, sharedUniforms, surfaceMaterial } from "./surface.js";

const METRES_PER_UM = 1e-6;
// Tiles are refined until their geometric error is at most this many pixels on screen.
const ERROR_TARGET_PX = 6;
const query = new URLSearchParams(location.search);
// A server with tokens gets one through the page's URL (?token=...): sent with every request.
const token = query.get("token");
const authorization = token ? { Authorization: `Bearer ${token}` } : {};
const api = (path) => fetch(path, { headers: authorization });
const $ = (id) => document.getElementById(id);
const view = $("view");
const status = { loaded: 0, failed: 0, tilesetLoaded: false, downloading: 0, queued: 0, visible: 0, settled: false, error: null, reopened: 0 };
window.viewer = { status, profile: null, roughness: null };

const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
view.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x111111);
// The tiles follow whichever camera is shown: one at a time, so nothing is loaded for the other.
const cameras = new ViewCamera(renderer.domElement, (camera) => {
  if (tiles) {
    for (const other of [cameras.perspective, cameras.orthographic]) tiles.deleteCamera(other);
    tiles.setCamera(camera);
    tiles.setResolutionFromRenderer(camera, renderer);
  }
  $("projection").value = cameras.isOrthographic ? "orthographic" : "perspective";
  updatePermalink();
  requestRender();
});
const uniforms = sharedUniforms();
const overlay = new THREE.Group(); // measurement lines and markers, in the tileset frame
scene.add(overlay);

// 3DTilesRendererJS warns on every 3D Tiles 1.1 tileset that it supports 1.1 in part; ours use of
// 1.1 only tile metadata (the zoom kind), which it reads, so that one warning is left out.
class SpecimenTiles extends TilesRenderer {
  preprocessTileset(json, ...rest) {
    const warn = console.warn;
    console.warn = (message, ...more) => String(message).includes("versions at 1.1") || warn(message, ...more);
    try {
      super.preprocessTileset(json, ...rest);
    } finally {
      console.warn = warn;
    }
  }

  // A tile of a build since replaced answers 410 Gone (the server never sends another build's
  // bytes under its URL): `onReplaced` is called, once, to open the specimen again as it is now.
  async fetchData(url, options) {
    const response = await super.fetchData(url, options);
    if (response.status === 410 && this.onReplaced) {
      const replaced = this.onReplaced;
      this.onReplaced = null;
      replaced();
    }
    return response;
  }
}

let tiles = null;
let specimen = null; // {id, rois, level, pixelSizeUm, heightRangeUm}
// The scene is drawn again only when something changed: software rendering (headless browsers,
// remote desktops) then leaves the main thread to the tiles' decoding.
let needsRender = true;
const requestRender = () => { needsRender = true; };
const measurements = new Measurements({
  overlay, api, specimen: () => specimen, onChange: () => updatePermalink(), redraw: requestRender,
  elements: { hint: $("tool-hint"), list: $("measurements"), plot: $("profile-plot") },
});
window.viewer.measurements = measurements;
window.viewer.debug = { get camera() { return cameras.camera; }, get controls() { return cameras.controls; }, cameras }; // for the browser tests

function resize() {
  const { clientWidth: width, clientHeight: height } = view;
  renderer.setSize(width, height);
  cameras.setAspect(width / height);
  measurements.setResolution(width, height);
  if (tiles) tiles.setResolutionFromRenderer(cameras.camera, renderer);
  requestRender();
}
window.addEventListener("resize", resize);

// What the display controls say, into the shared uniforms (every tile, shown or cached, at once).
function applyDisplay() {
  const value = (id) => Number($(id).value);
  uniforms.colouring.value = document.querySelector("input[name=colouring]:checked").value === "height" ? 1 : 0;
  uniforms.shadeZoom.value = $("zoom-kinds").checked ? 1 : 0;
  uniforms.showRois.value = $("roi-outlines").checked ? 1 : 0;
  uniforms.showWalls.value = $("walls").checked ? 1 : 0;
  uniforms.lighting.value = value("lighting");
  lightDirection(value("light-azimuth"), value("light-elevation"), uniforms.lightDirection.value);
  const exaggeration = 10 ** value("exaggeration");
  for (const group of [tiles?.group, overlay]) group?.scale.set(1, 1, exaggeration);
  $("light-azimuth-value").textContent = `${value("light-azimuth")}°`;
  $("light-elevation-value").textContent = `${value("light-elevation")}°`;
  $("lighting-value").textContent = value("lighting").toFixed(2);
  $("exaggeration-value").textContent = exaggeration.toFixed(1);
  $("legend").innerHTML = uniforms.shadeZoom.value
    ? '<span class="swatch" style="background:#7f7"></span>optical zoom (measured) &nbsp; <span class="swatch" style="background:#f96"></span>digital zoom (upsampled)'
    : "";
  $("roi-labels").hidden = !uniforms.showRois.value;
  updateColourBar();
  updatePermalink();
  requestRender();
}

function updateColourBar() {
  const bar = $("colour-bar");
  bar.hidden = !(uniforms.colouring.value === 1 && specimen);
  if (bar.hidden) return;
  const [low, high] = specimen.heightRangeUm;
  $("colour-bar-ramp").style.background = rampGradient();
  const ticks = niceTicks(low, high, 5).filter((t) => (t - low) / (high - low) > 0.08 && (high - t) / (high - low) > 0.08);
  const label = (value, id) => `<span ${id ? `id="${id}"` : ""} style="top:${(100 * (high - value)) / (high - low)}%">${formatUm(value, 2)}</span>`;
  $("colour-bar-ticks").innerHTML = label(high, "colour-bar-max") + ticks.map((t) => label(t)).join("") + label(low, "colour-bar-min");
  $("colour-bar-datum").textContent = specimen.level ? `0 µm: the ${specimen.level}` : "heights relative (offset arbitrary)";
}

function showMessage(text) {
  $("message").hidden = !text;
  $("message").textContent = text || "";
}

function setStatus(text, isError = false) {
  $("status").textContent = text;
  $("status").classList.toggle("error", isError);
}

async function open(id, state = {}) {
  if (tiles) {
    scene.remove(tiles.group);
    tiles.dispose();
  }
  measurements.clear();
  showMessage("");
  Object.assign(status, { loaded: 0, failed: 0, tilesetLoaded: false, settled: false, error: null, openedAt: performance.now() });
  const response = await api(`/api/specimens/${id}`);
  const summary = await response.json();
  if (!response.ok) {
    status.error = summary.error ?? `specimen ${id} did not load`;
    showMessage(status.error);
    return;
  }
  specimen = {
    id, rois: summary.rois, level: summary.rois[0]?.level || "",
    pixelSizeUm: Math.min(...summary.rois.map((roi) => roi.pixel_size_um)), heightRangeUm: [0, 1],
  };
  setRoiOutlines(summary.rois);
  tiles = new SpecimenTiles(`/specimens/${id}/tileset.json`);
  tiles.fetchOptions.headers = authorization;
  // After a rebuild the browser's copy of tileset.json (cached briefly) names the old build.
  if (state.rebuilt) tiles.fetchOptions.cache = "no-cache";
  // Rebuilt while shown: the new build opens with the camera, display and measurements kept.
  tiles.onReplaced = () => {
    status.reopened += 1;
    open(id, { ...applyState(new URL(permalink()).searchParams), rebuilt: true });
  };
  // Tiles are meshoptimizer-compressed (EXT_meshopt_compression).
  tiles.registerPlugin(new GLTFExtensionsPlugin({ meshoptDecoder: MeshoptDecoder }));
  tiles.errorTarget = ERROR_TARGET_PX;
  tiles.setCamera(cameras.camera);
  tiles.setResolutionFromRenderer(cameras.camera, renderer);
  tiles.addEventListener("load-tileset", () => {
    if (status.tilesetLoaded) return;
    status.tilesetLoaded = true;
    const box = tiles.root.boundingVolume.box;
    specimen.heightRangeUm = [(box[2] - box[11]) / METRES_PER_UM, (box[2] + box[11]) / METRES_PER_UM];
    uniforms.heightRange.value.set(box[2] - box[11], box[2] + box[11]);
    const sphere = new THREE.Sphere();
    tiles.getBoundingSphere(sphere);
    cameras.setExtent(sphere.radius);
    if (state.camera) cameras.decode(state.camera, state.orthographicHalfUm ?? null);
    else frameOverview(VIEWS.start);
    updateColourBar();
    if (state.measurements) measurements.decode(state.measurements);
  });
  for (const event of ["load-model", "dispose-model", "tile-visibility-change", "needs-update"]) tiles.addEventListener(event, requestRender);
  tiles.addEventListener("load-model", ({ scene: model, tile }) => {
    status.loaded += 1;
    const zoom = tile.metadata?.properties?.zoom;
    model.traverse((object) => {
      if (object.isMesh) {
        const loaded = object.material;
        object.material = surfaceMaterial(loaded, zoom, uniforms);
        loaded.dispose();
      }
    });
  });
  tiles.addEventListener("dispose-model", ({ scene: model }) => {
    // The renderer disposes materials it finds; our materials hold the textures in uniforms.
    model.traverse((object) => object.material?.uniforms?.map?.value?.dispose());
  });
  tiles.addEventListener("load-error", ({ url, error }) => {
    status.failed += 1;
    if (String(url).endsWith("tileset.json")) {
      status.error = `the tileset of ${id} did not load (${error?.message ?? error})`;
      showMessage(status.error);
    }
  });
  scene.add(tiles.group);
  list.select(id);
  applyDisplay();
  const overview = summary.rois[0];
  setStatus(`specimen ${id}: ${summary.rois.length} ROI; overview ${overview.id}` + (overview.magnification ? ` at ${overview.magnification}×` : "")
    + `, ${formatNumber(overview.pixel_size_um)} µm/px` + (specimen.level ? `; heights from the ${specimen.level}` : ""));
}

// Looks at the overview ROI from `direction` (VIEWS), all of it in the view.
function frameOverview(direction) {
  const { min, max } = specimen.rois[0].region;
  const [low, high] = specimen.heightRangeUm;
  const centre = new THREE.Vector3((min.x_um + max.x_um) / 2, -(min.y_um + max.y_um) / 2, (low + high) / 2).multiplyScalar(METRES_PER_UM);
  const halfWidth = ((max.x_um - min.x_um) / 2) * METRES_PER_UM;
  const halfHeight = ((max.y_um - min.y_um) / 2) * METRES_PER_UM;
  cameras.frame(centre, halfWidth, halfHeight, direction);
  updatePermalink();
  requestRender();
}

function setRoiOutlines(rois) {
  // Children only: the overview's outline is the specimen's edge.
  const shown = rois.filter((roi) => roi.parent).slice(0, MAX_ROIS);
  uniforms.roiCount.value = shown.length;
  shown.forEach((roi, i) => {
    const { min, max } = roi.region;
    uniforms.rois.value[i].set(min.x_um * METRES_PER_UM, -max.y_um * METRES_PER_UM, max.x_um * METRES_PER_UM, -min.y_um * METRES_PER_UM);
  });
  $("roi-labels").replaceChildren(...shown.map((roi) => {
    const label = document.createElement("span");
    label.textContent = `${roi.id}${roi.magnification ? ` · ${roi.magnification}×` : ""} · ${formatNumber(roi.pixel_size_um)} µm/px`;
    label.dataset.x = roi.region.min.x_um;
    label.dataset.y = roi.region.min.y_um;
    return label;
  }));
}

function updateRoiLabels() {
  const top = specimen ? specimen.heightRangeUm[1] : 0;
  const exaggeration = overlay.scale.z;
  for (const label of $("roi-labels").children) {
    const point = new THREE.Vector3(label.dataset.x * METRES_PER_UM, -label.dataset.y * METRES_PER_UM, top * METRES_PER_UM * exaggeration).project(cameras.camera);
    const visible = point.z < 1 && Math.abs(point.x) < 1 && Math.abs(point.y) < 1;
    label.style.display = visible ? "" : "none";
    label.style.left = `${((point.x + 1) / 2) * view.clientWidth}px`;
    label.style.top = `${((1 - point.y) / 2) * view.clientHeight}px`;
  }
}

function niceLength(metres) {
  const power = 10 ** Math.floor(Math.log10(metres));
  return [1, 2, 5, 10].map((m) => m * power).filter((v) => v <= metres).pop();
}

function updateScaleBar() {
  // Only where a length on screen is one on the specimen; elsewhere a bar would lie.
  const metresPerPixel = specimen ? cameras.trueMetresPerPixel(view.clientHeight) : null;
  $("scale-bar").hidden = metresPerPixel === null;
  $("scale-hint").hidden = !specimen || metresPerPixel !== null;
  if (metresPerPixel === null) return;
  const length = niceLength(metresPerPixel * 150);
  $("scale-line").style.width = `${length / metresPerPixel}px`;
  $("scale-label").textContent = `${+formatNumber(length / METRES_PER_UM)} µm`;
}

// Tiles' progress: what is shown, loading and failed, and whether the view has settled.
function updateProgress() {
  const stats = tiles.stats;
  const pending = stats.queued + stats.downloading + stats.parsing;
  Object.assign(status, { visible: tiles.visibleTiles.size, downloading: stats.downloading + stats.parsing, queued: stats.queued });
  const settled = status.tilesetLoaded && status.loaded > 0 && pending === 0;
  if (settled && !status.settled) status.settledAfterS = (performance.now() - status.openedAt) / 1000;
  status.settled = settled;
  $("tile-progress-text").textContent = `tiles: ${status.visible} shown, ${pending} loading` + (status.failed ? `, ${status.failed} failed` : "");
  $("tile-progress-text").classList.toggle("busy", pending > 0);
  $("tile-progress-bar").style.width = `${(100 * status.loaded) / Math.max(status.loaded + pending, 1)}%`;
  $("hud").style.opacity = pending ? 1 : 0.6;
}

function frame() {
  requestAnimationFrame(frame);
  cameras.controls.update();
  cameras.camera.updateMatrixWorld();
  if (tiles) {
    tiles.group.updateMatrixWorld();
    uniforms.toTileset.value.copy(tiles.group.matrixWorld).invert();
    tiles.update();
    updateProgress();
  }
  if (!needsRender) return;
  needsRender = false;
  updateScaleBar();
  updateRoiLabels();
  renderer.render(scene, cameras.camera);
}

// The surface point under a pointer event: specimen µm (x right, y down) and the shown height.
// A ray exactly along the edge two tiles share can miss both: half a pixel aside it does not.
function surfacePoint(event) {
  const bounds = renderer.domElement.getBoundingClientRect();
  const caster = new THREE.Raycaster();
  for (const [dx, dy] of [[0, 0], [0.5, 0], [-0.5, 0], [0, 0.5], [0, -0.5]]) {
    const x = event.clientX + dx - bounds.left;
    const y = event.clientY + dy - bounds.top;
    caster.setFromCamera(new THREE.Vector2((x / bounds.width) * 2 - 1, -(y / bounds.height) * 2 + 1), cameras.camera);
    const hit = caster.intersectObject(tiles.group, true).find((h) => !isWallMesh(h.object));
    if (hit) {
      const local = hit.point.clone().applyMatrix4(uniforms.toTileset.value);
      return { x_um: local.x / METRES_PER_UM, y_um: -local.y / METRES_PER_UM, z_um: local.z / METRES_PER_UM };
    }
  }
  return null;
}

async function measureRoughness() {
  const halfHeight = cameras.halfHeight();
  const halfWidth = halfHeight * cameras.aspect;
  const [cx, cy] = [cameras.controls.target.x / METRES_PER_UM, -cameras.controls.target.y / METRES_PER_UM];
  const [hx, hy] = [halfWidth / METRES_PER_UM, halfHeight / METRES_PER_UM];
  const form = $("roughness-form").value;
  const response = await api(`/api/specimens/${specimen.id}/roughness?region=${cx - hx},${cy - hy},${cx + hx},${cy + hy}&form=${form}`);
  const result = await response.json();
  window.viewer.roughness = result;
  $("roughness-stats").textContent = response.ok ? describeRoughness(result) : result.error;
}

function describeRoughness(result) {
  // Each value with its standard uncertainty where known, then the chain that produced them.
  // Digits follow the uncertainty (formatMeasured, as the report and the command line write them).
  const withUncertainty = (name) => `${name} ${formatMeasured(result[name], result.uncertainty[name]?.u_total, result.units[name])}`;
  const chain = result.chain;
  const filters = [["λs", chain.s_filter_um], ["λc", chain.l_filter_um]].map(([n, v]) => `${n} ${v ? `${v} µm` : "none"}`);
  const hurst = result.hurst.find((fit) => fit.method === "hhc" && fit.side === "along");
  const covered = result.coverage;
  const lines = [
    `${withUncertainty("Sa")}, ${withUncertainty("Sq")}, ${withUncertainty("Sdr")}`,
    hurst && !hurst.not_determinable
      ? `Hurst ${formatMeasured(hurst.hurst, hurst.hurst_stderr, "1")} (h(r), ${formatNumber(hurst.fit_min_um, 2)}–${formatNumber(hurst.fit_max_um, 2)} µm)`
      : `Hurst: ${hurst ? hurst.not_determinable : result.hurst_note}`,
    `chain: form ${chain.form}, ${filters.join(", ")}, ${formatNumber(result.pixel_size_um)} µm/px`,
  ];
  if (covered) lines.push(`on the matched heights: ${formatNumber(100 * covered.measured_fraction, 3)} % of the view (${formatNumber(100 * covered.filled_fraction, 2)} % filled left out)`);
  if (result.noise_bias.Sq != null) lines.push(`noise adds ${formatNumber(result.noise_bias.Sq, 2)} µm to Sq`);
  for (const caveat of result.caveats ?? []) lines.push(`caveat: ${caveat}`);
  return lines.join("\n");
}

// Runs `work` with `button` disabled and a spinner with the seconds it has taken so far.
async function busy(button, work) {
  const label = button.textContent;
  const started = performance.now();
  button.disabled = true;
  button.classList.add("busy");
  const timer = setInterval(() => { button.textContent = `${label}: ${((performance.now() - started) / 1000).toFixed(0)} s`; }, 500);
  try {
    await work();
  } finally {
    clearInterval(timer);
    button.textContent = label;
    button.disabled = false;
    button.classList.remove("busy");
  }
}

// The camera, the display and the measurements as a URL (µm in the specimen frame).
function permalink() {
  const url = new URL(location.href);
  const params = url.searchParams;
  params.set("specimen", specimen?.id ?? "");
  const { camera, orthographic } = cameras.encode();
  params.set("camera", camera.join(","));
  if (orthographic === null) params.delete("orthographic");
  else params.set("orthographic", orthographic);
  params.set("colouring", uniforms.colouring.value ? "height" : "texture");
  params.set("light", [$("light-azimuth").value, $("light-elevation").value, $("lighting").value].join(","));
  params.set("exaggeration", $("exaggeration").value);
  params.set("show", [["zoom-kinds", "zoom"], ["roi-outlines", "rois"], ["walls", "walls"]].filter(([id]) => $(id).checked).map(([, name]) => name).join(","));
  const encoded = measurements.encode();
  if (encoded) params.set("measurements", encoded);
  else params.delete("measurements");
  return url.toString();
}

function updatePermalink() {
  if (specimen) $("permalink-text").value = permalink();
}

function applyState(params) {
  const light = (params.get("light") || "").split(",");
  [["light-azimuth", light[0]], ["light-elevation", light[1]], ["lighting", light[2]], ["exaggeration", params.get("exaggeration")]]
    .forEach(([id, value]) => { if (value !== undefined && value !== null && value !== "" && Number.isFinite(Number(value))) $(id).value = value; });
  if (params.get("colouring")) document.querySelector(`input[name=colouring][value=${params.get("colouring") === "height" ? "height" : "texture"}]`).checked = true;
  if (params.has("show")) {
    const shown = params.get("show").split(",");
    $("zoom-kinds").checked = shown.includes("zoom");
    $("roi-outlines").checked = shown.includes("rois");
    $("walls").checked = shown.includes("walls");
  }
  const cameraValues = (params.get("camera") || "").split(",").map(Number);
  return {
    camera: cameraValues.length === 6 && cameraValues.every(Number.isFinite) ? cameraValues : null,
    orthographicHalfUm: Number(params.get("orthographic")) > 0 ? Number(params.get("orthographic")) : null,
    measurements: params.get("measurements"),
  };
}

// The view as a PNG, with the overlays drawn into it where the page shows them (each text moved
// inside the picture where it would reach past its edge). Its texts and their boxes (CSS px) go to
// window.viewer.snapshotTexts.
function snapshot() {
  const canvas = document.createElement("canvas");
  const source = renderer.domElement;
  [canvas.width, canvas.height] = [source.width, source.height];
  const context = canvas.getContext("2d");
  context.drawImage(source, 0, 0);
  context.scale(source.width / view.clientWidth, source.width / view.clientWidth);
  Object.assign(context, { font: "13px system-ui, sans-serif", fillStyle: "#fff", shadowColor: "#000", shadowBlur: 3 });
  const origin = view.getBoundingClientRect();
  const texts = [];
  const text = (value, x, y) => {
    const width = context.measureText(value).width;
    const left = Math.max(4, Math.min(x, view.clientWidth - width - 4));
    context.fillText(value, left, y);
    texts.push({ text: value, left, right: left + width });
  };
  const box = (id) => {
    const { left, top, right, bottom, width, height } = $(id).getBoundingClientRect();
    return { left: left - origin.left, top: top - origin.top, right: right - origin.left, bottom: bottom - origin.top, width, height };
  };
  if (!$("scale-bar").hidden) {
    const line = box("scale-line");
    context.fillRect(line.left, line.top, line.width, line.height);
    text($("scale-label").textContent, line.left, line.bottom + 16);
  }
  if (!$("colour-bar").hidden) drawColourBar(context, box, text);
  if ($("legend").textContent) text($("legend").textContent.replace(/\s+/g, " ").trim(), box("legend").left, box("legend").bottom - 3);
  text(`Fractoscope: ${specimen?.id ?? ""}`, 16, 20);
  window.viewer.snapshotTexts = texts;
  return canvas.toDataURL("image/png");
}

// The colour bar into a snapshot: its ramp, ticks, title and datum (`box(id)` and `text(value, x,
// y)` as in snapshot).
function drawColourBar(context, box, text) {
  const ramp = box("colour-bar-ramp");
  const gradient = context.createLinearGradient(0, ramp.bottom, 0, ramp.top);
  RAMP.forEach((c, i) => gradient.addColorStop(i / (RAMP.length - 1), `rgb(${c.map((v) => Math.round(v * 255)).join(",")})`));
  context.fillStyle = gradient;
  context.fillRect(ramp.left, ramp.top, ramp.width, ramp.height);
  context.fillStyle = "#fff";
  for (const tick of $("colour-bar-ticks").children) {
    const { left, top, height } = tick.getBoundingClientRect();
    text(tick.textContent, left - view.getBoundingClientRect().left + 8, top - view.getBoundingClientRect().top + height * 0.8);
  }
  const title = box("colour-bar-title");
  text($("colour-bar-title").textContent, title.left, title.bottom - 2);
  const datum = box("colour-bar-datum");
  text($("colour-bar-datum").textContent, datum.left, datum.top + 12);
}
window.viewer.snapshot = snapshot;

let pressedAt = null;
renderer.domElement.addEventListener("pointerdown", (event) => { pressedAt = [event.clientX, event.clientY]; });
renderer.domElement.addEventListener("pointerup", (event) => {
  // A click (not a drag) picks a point when a measuring tool is on.
  if (!measurements.tool || !tiles || !pressedAt || Math.hypot(event.clientX - pressedAt[0], event.clientY - pressedAt[1]) > 4) return;
  const point = surfacePoint(event);
  status.missedPicks = (status.missedPicks ?? 0) + (point ? 0 : 1);
  if (point) measurements.pick(point);
});
document.querySelectorAll("[data-tool]").forEach((button) => button.addEventListener("click", () => measurements.start(button.dataset.tool)));
$("clear-measurements").addEventListener("click", () => measurements.clear());
$("roughness-button").addEventListener("click", (event) => busy(event.currentTarget, measureRoughness));
document.querySelectorAll("#panel input").forEach((input) => input.addEventListener("input", applyDisplay));
cameras.controls.addEventListener("change", requestRender);
cameras.controls.addEventListener("end", updatePermalink);
$("permalink").addEventListener("click", async () => {
  const link = permalink();
  $("permalink-text").value = link;
  $("permalink-text").select();
  try {
    await navigator.clipboard.writeText(link);
    setStatus("link copied");
  } catch {
    setStatus("link below: copy it from there");
  }
});
$("snapshot").addEventListener("click", () => {
  const download = document.createElement("a");
  download.href = snapshot();
  download.download = `fractoscope-${specimen?.id ?? "view"}.png`;
  download.click();
});
document.querySelectorAll("[data-view]").forEach((button) => button.addEventListener("click", () => showView(button.dataset.view)));
$("projection").addEventListener("change", (event) => cameras.setProjection(event.target.value === "orthographic"));
// Keys: T, F, S the top, front and side views, O orthographic or perspective, R the starting view.
window.addEventListener("keydown", (event) => {
  if (event.target.closest?.("input, select, textarea") || event.ctrlKey || event.metaKey || event.altKey) return;
  const action = { t: "top", f: "front", s: "side", r: "start", o: "projection" }[event.key.toLowerCase()];
  if (!action || !specimen) return;
  if (action === "projection") cameras.setProjection(!cameras.isOrthographic);
  else showView(action);
});

function showView(name) {
  if (specimen) frameOverview(VIEWS[name]);
}

const list = new SpecimenList({
  element: $("specimens"), api, token,
  onPick: (id) => open(id),
  // A build that the link asked for and that was not there yet: shown once it is built.
  onBuilt: (id) => { if (!specimen && id === query.get("specimen")) open(id, applyState(query)); },
});
const specimens = await list.refresh();
const wanted = query.get("specimen");
resize();
applyDisplay();
if (wanted && !specimens.some((entry) => entry.id === wanted)) {
  // Never silently show another specimen than the one the link names.
  const job = list.jobOf(wanted);
  const building = Boolean(job) && isUnderWay(job);
  status.error = building ? null : `no specimen "${wanted}" here` + (specimens.length ? `; there are: ${specimens.map((s) => s.id).join(", ")}` : "");
  showMessage(building ? `${wanted} is being built: it opens here when it is done` : status.error);
  if (!building) setStatus(status.error, true);
} else if (specimens.length) {
  await open(wanted || specimens[0].id, applyState(query));
} else {
  setStatus("no specimens yet: run fracto reconstruct");
}
frame();
