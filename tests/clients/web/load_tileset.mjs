// Loads a 3D Tiles tileset with 3DTilesRendererJS (three.js) in headless Chromium and prints one
// JSON line: tiles loaded and drawn, failures, and whether the picture is blank.
// Usage: node load_tileset.mjs TILESET_URL SCREENSHOT.png
import { createServer } from "node:http";
import { readFile, writeFile } from "node:fs/promises";
import { extname, join, normalize } from "node:path";
import { addPageHelpers, canvasStats, launchChromium } from "./browser.mjs";

const [tilesetUrl, screenshotPath] = process.argv.slice(2);
// The viewer package (clients/web), whose node_modules hold three.js and 3DTilesRendererJS.
const root = join(import.meta.dirname, "..", "..", "..", "clients", "web");
const types = { ".js": "text/javascript", ".html": "text/html", ".mjs": "text/javascript" };

const page = `<!doctype html><html><body style="margin:0;background:#000">
<script type="importmap">{"imports": {
  "three": "/node_modules/three/build/three.module.js",
  "three/addons/": "/node_modules/three/examples/jsm/",
  "3d-tiles-renderer": "/node_modules/3d-tiles-renderer/build/index.js",
  "3d-tiles-renderer/plugins": "/node_modules/3d-tiles-renderer/build/index.plugins.js"}}</script>
<script type="module">
import * as THREE from "three";
import { MeshoptDecoder } from "three/addons/libs/meshopt_decoder.module.js";
import { TilesRenderer } from "3d-tiles-renderer";
import { GLTFExtensionsPlugin } from "3d-tiles-renderer/plugins";
const status = { loaded: 0, failed: [], tilesetLoaded: false, done: false };
window.status3d = status;
const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
renderer.setSize(512, 512);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 3));
const camera = new THREE.PerspectiveCamera(45, 1, 1e-7, 10);
const tiles = new TilesRenderer(${JSON.stringify(tilesetUrl)});
tiles.errorTarget = 2;
tiles.registerPlugin(new GLTFExtensionsPlugin({ meshoptDecoder: MeshoptDecoder }));
tiles.setCamera(camera);
tiles.setResolutionFromRenderer(camera, renderer);
tiles.addEventListener("load-tileset", () => {
  status.tilesetLoaded = true;
  const sphere = new THREE.Sphere();
  tiles.getBoundingSphere(sphere);
  // Look straight down on the specimen (tileset z is up) from a distance that shows all of it.
  camera.position.copy(sphere.center).add(new THREE.Vector3(0, 0, sphere.radius * 2.2));
  camera.up.set(0, 1, 0);
  camera.lookAt(sphere.center);
  camera.near = sphere.radius * 0.01;
  camera.far = sphere.radius * 10;
  camera.updateProjectionMatrix();
});
tiles.addEventListener("load-model", () => { status.loaded += 1; });
tiles.addEventListener("load-error", (event) => { status.failed.push(String(event.url || event.error)); });
scene.add(tiles.group);
function frame() {
  camera.updateMatrixWorld();
  tiles.update();
  renderer.render(scene, camera);
  status.visible = tiles.visibleTiles ? tiles.visibleTiles.size : -1;
  status.downloading = tiles.stats ? tiles.stats.downloading + tiles.stats.parsing : 0;
  if (!status.stop) requestAnimationFrame(frame);
}
frame();
</script></body></html>`;

const server = createServer(async (request, response) => {
  const path = normalize(decodeURIComponent(new URL(request.url, "http://x").pathname));
  if (path === "/") {
    response.writeHead(200, { "Content-Type": "text/html" });
    response.end(page);
    return;
  }
  if (!path.startsWith("/node_modules/")) {
    response.writeHead(404);
    response.end();
    return;
  }
  try {
    const body = await readFile(join(root, path));
    response.writeHead(200, { "Content-Type": types[extname(path)] ?? "application/octet-stream" });
    response.end(body);
  } catch {
    response.writeHead(404);
    response.end();
  }
});
await new Promise((resolve) => server.listen(0, "127.0.0.1", resolve));

const browser = await launchChromium();
const result = { errors: [] };
try {
  const tab = await browser.newPage();
  await addPageHelpers(tab);
  tab.on("pageerror", (error) => result.errors.push(String(error)));
  await tab.goto(`http://127.0.0.1:${server.address().port}/`);
  // Wait until tiles have loaded and nothing is downloading or parsing for a moment.
  let quiet = 0;
  for (let i = 0; i < 240 && quiet < 5; i++) {
    await tab.waitForTimeout(250);
    const s = await tab.evaluate(() => window.status3d);
    quiet = s && s.loaded > 0 && s.downloading === 0 ? quiet + 1 : 0;
  }
  Object.assign(result, await tab.evaluate(() => window.status3d));
  // Stop rendering so the picture holds still for the screenshot.
  await tab.evaluate(() => { window.status3d.stop = true; });
  await tab.waitForTimeout(200);
  await writeFile(screenshotPath, await tab.screenshot({ clip: { x: 0, y: 0, width: 512, height: 512 }, timeout: 60000 }));
  result.litFraction = (await canvasStats(tab, "canvas", [0, 0, 0])).litFraction;  // black background
} finally {
  await browser.close();
  server.close();
}
console.log(JSON.stringify(result));
