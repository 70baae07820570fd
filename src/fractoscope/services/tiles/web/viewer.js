// Fractoscope web viewer: streams a specimen's 3D Tiles with 3DTilesRendererJS, colours it by the
// SEM image or by height, shades optical vs digital tiles, measures profiles and roughness.
// Tileset frame (3D Tiles, Z up, metres): x = specimen x, y = -specimen y, z = height.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { MeshoptDecoder } from "three/addons/libs/meshopt_decoder.module.js";
import { TilesRenderer } from "3d-tiles-renderer";
import { GLTFExtensionsPlugin } from "3d-tiles-renderer/plugins";

const METRES_PER_UM = 1e-6;
// A server with tokens gets one through the page's URL (?token=...): sent with every request.
const token = new URLSearchParams(location.search).get("token");
const authorization = token ? { Authorization: `Bearer ${token}` } : {};
const api = (path) => fetch(path, { headers: authorization });
const view = document.getElementById("view");
const status = { loaded: 0, failed: 0, tilesetLoaded: false, downloading: 0, visible: 0 };
window.viewer = { status, profile: null, roughness: null };

const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
view.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x111111);
const camera = new THREE.PerspectiveCamera(45, 1, 1e-9, 10);
camera.up.set(0, 0, 1);
const controls = new OrbitControls(camera, renderer.domElement);
controls.screenSpacePanning = true;
const profileLine = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: 0xff3355, depthTest: false }));
profileLine.renderOrder = 10;
scene.add(profileLine);

let tiles = null;
let specimenId = null;
let heightRangeM = [0, 1];
let colouring = "texture";
let shadeZoom = false;
let picking = null;

function resize() {
  const { clientWidth: width, clientHeight: height } = view;
  renderer.setSize(width, height);
  camera.aspect = width / height;
  camera.updateProjectionMatrix();
  if (tiles) tiles.setResolutionFromRenderer(camera, renderer);
}
window.addEventListener("resize", resize);

function heightColour(fraction, colour) {
  // A perceptual blue-green-yellow ramp (close to viridis).
  const stops = [[0.27, 0.0, 0.33], [0.13, 0.57, 0.55], [0.99, 0.91, 0.14]];
  const t = Math.min(Math.max(fraction, 0), 1) * (stops.length - 1);
  const i = Math.min(Math.floor(t), stops.length - 2);
  const f = t - i;
  colour.setRGB(...stops[i].map((v, k) => v + (stops[i + 1][k] - v) * f), THREE.SRGBColorSpace);
}

function styleMesh(mesh) {
  const data = mesh.userData;
  if (!data.imageMaterial) {
    data.imageMaterial = new THREE.MeshBasicMaterial({ map: mesh.material.map, side: THREE.DoubleSide });
    mesh.material.dispose();
  }
  if (colouring === "height" && !data.heightMaterial) {
    // glTF positions are Y-up: the height is y, in metres, once the node's transform turns the
    // quantized positions (KHR_mesh_quantization) back into metres.
    const positions = mesh.geometry.getAttribute("position");
    const colours = new Float32Array(positions.count * 3);
    const colour = new THREE.Color();
    const vertex = new THREE.Vector3();
    const [low, high] = heightRangeM;
    mesh.updateMatrix();
    for (let i = 0; i < positions.count; i++) {
      const heightM = vertex.fromBufferAttribute(positions, i).applyMatrix4(mesh.matrix).y;
      heightColour((heightM - low) / (high - low || 1), colour);
      colours.set([colour.r, colour.g, colour.b], i * 3);
    }
    mesh.geometry.setAttribute("color", new THREE.BufferAttribute(colours, 3));
    data.heightMaterial = new THREE.MeshBasicMaterial({ vertexColors: true, side: THREE.DoubleSide });
  }
  mesh.material = colouring === "height" ? data.heightMaterial : data.imageMaterial;
  const tint = !shadeZoom ? 0xffffff : data.zoom === "DIGITAL" ? 0xff9966 : 0x99ff99;
  data.imageMaterial.color.set(tint);
  if (data.heightMaterial) data.heightMaterial.color.set(tint);
}

function restyle() {
  if (tiles) tiles.group.traverse((object) => { if (object.isMesh) styleMesh(object); });
  document.getElementById("legend").textContent = shadeZoom ? "green: optical zoom (measured), orange: digital zoom (upsampled)" : "";
}

function open(id) {
  if (tiles) {
    scene.remove(tiles.group);
    tiles.dispose();
  }
  specimenId = id;
  Object.assign(status, { loaded: 0, failed: 0, tilesetLoaded: false });
  tiles = new TilesRenderer(`/specimens/${id}/tileset.json`);
  tiles.fetchOptions.headers = authorization;
  // Tiles are meshoptimizer-compressed (EXT_meshopt_compression).
  tiles.registerPlugin(new GLTFExtensionsPlugin({ meshoptDecoder: MeshoptDecoder }));
  tiles.errorTarget = 4;
  tiles.setCamera(camera);
  tiles.setResolutionFromRenderer(camera, renderer);
  tiles.addEventListener("load-tileset", () => {
    status.tilesetLoaded = true;
    const box = tiles.root.boundingVolume.box;
    heightRangeM = [box[2] - box[11], box[2] + box[11]];
    const sphere = new THREE.Sphere();
    tiles.getBoundingSphere(sphere);
    controls.target.copy(sphere.center);
    camera.position.copy(sphere.center).add(new THREE.Vector3(0, -0.4 * sphere.radius, 2.2 * sphere.radius));
    camera.near = sphere.radius * 1e-3;
    camera.far = sphere.radius * 20;
    camera.updateProjectionMatrix();
    controls.update();
  });
  tiles.addEventListener("load-model", ({ scene: model, tile }) => {
    status.loaded += 1;
    const zoom = tile.metadata?.properties?.zoom;
    model.traverse((object) => {
      if (object.isMesh) {
        object.userData.zoom = zoom;
        styleMesh(object);
      }
    });
  });
  tiles.addEventListener("load-error", () => { status.failed += 1; });
  scene.add(tiles.group);
  document.getElementById("status").textContent = `specimen ${id}`;
}

function niceLength(metres) {
  const power = 10 ** Math.floor(Math.log10(metres));
  return [1, 2, 5, 10].map((m) => m * power).filter((v) => v <= metres).pop();
}

function updateScaleBar() {
  const distance = camera.position.distanceTo(controls.target);
  const metresPerPixel = (2 * distance * Math.tan(THREE.MathUtils.degToRad(camera.fov / 2))) / view.clientHeight;
  const length = niceLength(metresPerPixel * 150);
  document.getElementById("scale-line").style.width = `${length / metresPerPixel}px`;
  document.getElementById("scale-label").textContent = `${+(length / METRES_PER_UM).toPrecision(3)} µm`;
}

function frame() {
  requestAnimationFrame(frame);
  controls.update();
  camera.updateMatrixWorld();
  if (tiles) {
    tiles.update();
    status.visible = tiles.visibleTiles.size;
    status.downloading = tiles.stats.downloading + tiles.stats.parsing;
  }
  updateScaleBar();
  renderer.render(scene, camera);
}

function specimenPointUm(event) {
  const bounds = renderer.domElement.getBoundingClientRect();
  const pointer = new THREE.Vector2(((event.clientX - bounds.left) / bounds.width) * 2 - 1, -((event.clientY - bounds.top) / bounds.height) * 2 + 1);
  const caster = new THREE.Raycaster();
  caster.setFromCamera(pointer, camera);
  const hit = caster.intersectObject(tiles.group, true)[0];
  return hit ? { world: hit.point.clone(), x_um: hit.point.x / METRES_PER_UM, y_um: -hit.point.y / METRES_PER_UM } : null;
}

function plotProfile(result) {
  const canvas = document.getElementById("profile-plot");
  const context = canvas.getContext("2d");
  context.clearRect(0, 0, canvas.width, canvas.height);
  const points = result.distance_um.map((d, i) => [d, result.z_um[i]]).filter(([, z]) => z !== null);
  if (points.length < 2) return;
  const [dMax, zLow, zHigh] = [result.distance_um.at(-1), Math.min(...points.map((p) => p[1])), Math.max(...points.map((p) => p[1]))];
  const x = (d) => 30 + (d / dMax) * (canvas.width - 40);
  const y = (z) => canvas.height - 20 - ((z - zLow) / (zHigh - zLow || 1)) * (canvas.height - 30);
  context.strokeStyle = "#c23";
  context.beginPath();
  points.forEach(([d, z], i) => (i ? context.lineTo(x(d), y(z)) : context.moveTo(x(d), y(z))));
  context.stroke();
  context.fillStyle = "#333";
  context.fillText(`${dMax.toFixed(1)} µm`, canvas.width - 50, canvas.height - 5);
  context.fillText(`${(zHigh - zLow).toFixed(2)} µm`, 2, 12);
}

async function measureProfile(start, end) {
  const query = `from=${start.x_um},${start.y_um}&to=${end.x_um},${end.y_um}`;
  const response = await api(`/api/specimens/${specimenId}/profile?${query}`);
  const result = await response.json();
  window.viewer.profile = result;
  if (!response.ok) {
    document.getElementById("profile-stats").textContent = result.error;
    return;
  }
  plotProfile(result);
  const p = result.parameters;
  document.getElementById("profile-stats").textContent = p
    ? `Ra ${p.Ra.toFixed(3)} µm, Rq ${p.Rq.toFixed(3)} µm, Rz ${p.Rz.toFixed(3)} µm`
    : "no heights along this line";
}

async function measureRoughness() {
  const distance = camera.position.distanceTo(controls.target);
  const halfHeight = distance * Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
  const halfWidth = halfHeight * camera.aspect;
  const [cx, cy] = [controls.target.x / METRES_PER_UM, -controls.target.y / METRES_PER_UM];
  const [hx, hy] = [halfWidth / METRES_PER_UM, halfHeight / METRES_PER_UM];
  const form = document.getElementById("roughness-form").value;
  const response = await api(`/api/specimens/${specimenId}/roughness?region=${cx - hx},${cy - hy},${cx + hx},${cy + hy}&form=${form}`);
  const result = await response.json();
  window.viewer.roughness = result;
  document.getElementById("roughness-stats").textContent = response.ok ? describeRoughness(result) : result.error;
}

function describeRoughness(result) {
  // Each value with its standard uncertainty where known, then the chain that produced them.
  const withUncertainty = (name, digits, unit) => {
    const u = result.uncertainty[name]?.u_total;
    return `${name} ${result[name].toFixed(digits)}${u == null ? "" : ` ± ${u.toPrecision(2)}`} ${unit}`;
  };
  const chain = result.chain;
  const filters = [["λs", chain.s_filter_um], ["λc", chain.l_filter_um]].filter(([, v]) => v).map(([n, v]) => `${n} ${v} µm`);
  const hurst = result.hurst.find((fit) => fit.method === "hhc" && fit.side === "along");
  const lines = [
    `${withUncertainty("Sa", 3, "µm")}, ${withUncertainty("Sq", 3, "µm")}, ${withUncertainty("Sdr", 2, "%")}`,
    hurst
      ? `Hurst ${hurst.hurst.toFixed(2)} ± ${hurst.hurst_stderr.toFixed(2)} (h(r), ${hurst.fit_min_um.toPrecision(2)}–${hurst.fit_max_um.toPrecision(2)} µm)`
      : result.hurst_note,
    `chain: form ${chain.form}, ${filters.length ? filters.join(", ") : "no filters"}, ${result.pixel_size_um.toPrecision(3)} µm/px`,
  ];
  if (result.noise_bias.Sq != null) lines.push(`noise adds ${result.noise_bias.Sq.toPrecision(2)} µm to Sq`);
  return lines.join("\n");
}

let pressedAt = null;
renderer.domElement.addEventListener("pointerdown", (event) => { pressedAt = [event.clientX, event.clientY]; });
renderer.domElement.addEventListener("pointerup", (event) => {
  // A click (not a drag) picks a point when the profile tool is on.
  if (!picking || !pressedAt || Math.hypot(event.clientX - pressedAt[0], event.clientY - pressedAt[1]) > 4) return;
  const point = specimenPointUm(event);
  if (!point) return;
  picking.push(point);
  profileLine.geometry.setFromPoints(picking.map((p) => p.world));
  if (picking.length === 2) {
    const [start, end] = picking;
    picking = null;
    document.getElementById("profile-tool").classList.remove("active");
    measureProfile(start, end);
  }
});
document.getElementById("profile-tool").addEventListener("click", (event) => {
  picking = [];
  event.target.classList.add("active");
  document.getElementById("profile-stats").textContent = "click two points on the surface";
});
document.getElementById("roughness-button").addEventListener("click", measureRoughness);
document.querySelectorAll("input[name=colouring]").forEach((input) =>
  input.addEventListener("change", () => { colouring = input.value; restyle(); }));
document.getElementById("zoom-kinds").addEventListener("change", (event) => { shadeZoom = event.target.checked; restyle(); });
document.getElementById("specimen").addEventListener("change", (event) => open(event.target.value));

const specimens = await (await api("/api/specimens")).json();
const chooser = document.getElementById("specimen");
for (const specimen of specimens) chooser.add(new Option(`${specimen.id} (${specimen.rois.length} ROI)`, specimen.id));
const wanted = new URLSearchParams(location.search).get("specimen");
if (specimens.length) {
  chooser.value = specimens.some((s) => s.id === wanted) ? wanted : specimens[0].id;
  open(chooser.value);
} else {
  document.getElementById("status").textContent = "no specimens yet: run fracto reconstruct";
}
resize();
frame();
