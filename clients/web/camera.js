// The viewer's cameras: perspective or orthographic, orbited with damping and zoomed towards the
// cursor; the top, front and side views and the starting view; the scale bar, shown only where a
// length on screen is a length on the specimen (orthographic, looking straight down).
// Tileset frame (3D Tiles, Z up, metres): x = specimen x, y = -specimen y, z = height.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

const FOV_DEG = 45;
// The scale bar is true when the view direction is within this angle of straight down.
const TOP_VIEW_TOLERANCE_DEG = 0.05;
// View directions, from the target towards the camera: from above (image up on screen), from the
// front (the image's bottom edge) and from the side (its right edge), and the starting view.
export const VIEWS = {
  top: new THREE.Vector3(0, -1e-6, 1),
  front: new THREE.Vector3(0, -1, 0),
  side: new THREE.Vector3(1, 0, 0),
  start: new THREE.Vector3(0, -0.18, 0.98),
};

export class ViewCamera {
  // `element` receives the pointer and wheel events; `onSwitch(camera)` is told of a new camera.
  constructor(element, onSwitch) {
    this.perspective = new THREE.PerspectiveCamera(FOV_DEG, 1, 1e-9, 10);
    this.orthographic = new THREE.OrthographicCamera(-1, 1, 1, -1, 1e-9, 10);
    for (const camera of [this.perspective, this.orthographic]) camera.up.set(0, 0, 1);
    this.camera = this.perspective;
    this.onSwitch = onSwitch;
    this.controls = new OrbitControls(this.camera, element);
    Object.assign(this.controls, { screenSpacePanning: true, enableDamping: true, dampingFactor: 0.12, rotateSpeed: 0.5, zoomToCursor: true });
    this.aspect = 1;
    this.radius = 1; // of the specimen's bounding sphere, m
  }

  get isOrthographic() {
    return this.camera === this.orthographic;
  }

  setAspect(aspect) {
    this.aspect = aspect;
    this.perspective.aspect = aspect;
    const half = this.orthographic.top;
    Object.assign(this.orthographic, { left: -half * aspect, right: half * aspect });
    for (const camera of [this.perspective, this.orthographic]) camera.updateProjectionMatrix();
  }

  // Near and far planes for a specimen whose bounding sphere has `radius` (m).
  setExtent(radius) {
    this.radius = radius;
    for (const camera of [this.perspective, this.orthographic]) Object.assign(camera, { near: radius * 1e-3, far: radius * 40 });
    for (const camera of [this.perspective, this.orthographic]) camera.updateProjectionMatrix();
  }

  // Half the height (m) of what the view shows at the target's distance.
  halfHeight() {
    if (this.isOrthographic) return this.orthographic.top / this.orthographic.zoom;
    return this.camera.position.distanceTo(this.controls.target) * Math.tan(THREE.MathUtils.degToRad(FOV_DEG / 2));
  }

  // Switches projection, keeping the target, the direction and what the view shows at the target.
  setProjection(orthographic) {
    if (orthographic === this.isOrthographic) return;
    const half = this.halfHeight();
    const from = this.camera;
    const to = orthographic ? this.orthographic : this.perspective;
    const direction = from.position.clone().sub(this.controls.target).normalize();
    const distance = orthographic ? Math.max(2 * this.radius, half / Math.tan(THREE.MathUtils.degToRad(FOV_DEG / 2))) : half / Math.tan(THREE.MathUtils.degToRad(FOV_DEG / 2));
    to.position.copy(this.controls.target).addScaledVector(direction, distance);
    if (orthographic) Object.assign(this.orthographic, { top: half, bottom: -half, left: -half * this.aspect, right: half * this.aspect, zoom: 1 });
    to.updateProjectionMatrix();
    this.camera = to;
    this.controls.object = to;
    this.controls.update();
    this.onSwitch(to);
  }

  // Looks at `centre` (m) from `direction` with a rectangle of `halfWidth` x `halfHeight` (m) all in view.
  frame(centre, halfWidth, halfHeight, direction) {
    const half = 1.15 * Math.max(halfHeight, halfWidth / this.aspect);
    const distance = half / Math.tan(THREE.MathUtils.degToRad(FOV_DEG / 2));
    this.controls.target.copy(centre);
    this.camera.position.copy(centre).addScaledVector(direction.clone().normalize(), this.isOrthographic ? Math.max(distance, 2 * this.radius) : distance);
    Object.assign(this.orthographic, { top: half, bottom: -half, left: -half * this.aspect, right: half * this.aspect, zoom: 1 });
    this.orthographic.updateProjectionMatrix();
    this.controls.update();
  }

  // Metres per screen pixel where a length on screen is one on the specimen (orthographic,
  // looking straight down), else null. `heightPx`: the view's height in CSS pixels.
  trueMetresPerPixel(heightPx) {
    if (!this.isOrthographic) return null;
    const down = new THREE.Vector3();
    this.camera.getWorldDirection(down);
    if (down.angleTo(new THREE.Vector3(0, 0, -1)) > THREE.MathUtils.degToRad(TOP_VIEW_TOLERANCE_DEG)) return null;
    return (2 * this.halfHeight()) / heightPx;
  }

  // The camera and target in specimen µm (x right, y down), and the orthographic zoom, for a link.
  encode() {
    const { position: p } = this.camera;
    const t = this.controls.target;
    return { camera: [p.x, -p.y, p.z, t.x, -t.y, t.z].map((v) => +(v * 1e6).toFixed(3)), orthographic: this.isOrthographic ? +(this.halfHeight() * 1e6).toPrecision(6) : null };
  }

  // Back from `encode`'s values (orthographic: the half height shown, µm, or null).
  decode(values, orthographicHalfUm) {
    this.setProjection(orthographicHalfUm !== null);
    const [x, y, z, tx, ty, tz] = values.map((v) => v * 1e-6);
    this.camera.position.set(x, -y, z);
    this.controls.target.set(tx, -ty, tz);
    if (orthographicHalfUm !== null) {
      const half = orthographicHalfUm * 1e-6;
      Object.assign(this.orthographic, { top: half, bottom: -half, left: -half * this.aspect, right: half * this.aspect, zoom: 1 });
      this.orthographic.updateProjectionMatrix();
    }
    this.controls.update();
  }
}
