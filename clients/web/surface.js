// How tiles are drawn: one shader for every tile, lit by a directional light through the normals
// the GLBs carry, coloured by the SEM image or by height, tinted by optical / digital zoom, with
// ROI outlines drawn on the surface and walls (triangles across jumps nothing measured) hatched.
// All tiles share one set of uniforms, so a change of display reaches every tile at once,
// including those the renderer holds in its cache outside the scene.
import * as THREE from "three";

// Viridis at five stops (sRGB, 0..1): the colour bar and the shader use the same ramp.
export const RAMP = [[0.267, 0.005, 0.329], [0.231, 0.322, 0.545], [0.129, 0.569, 0.549], [0.369, 0.788, 0.384], [0.992, 0.906, 0.145]];
export const MAX_ROIS = 8;
const ZOOM_KINDS = { OPTICAL: 1, DIGITAL: 2 };

export function sharedUniforms() {
  return {
    colouring: { value: 0 }, // 0: SEM image, 1: height
    heightRange: { value: new THREE.Vector2(0, 1) }, // metres, tileset frame
    toTileset: { value: new THREE.Matrix4() }, // world to tileset frame (undoes the exaggeration)
    lightDirection: { value: new THREE.Vector3(0, 0, 1) }, // towards the light, world frame
    lighting: { value: 0.7 }, // 0: flat, 1: fully lit
    ambient: { value: 0.3 },
    shadeZoom: { value: 0 },
    showWalls: { value: 1 },
    showRois: { value: 1 },
    roiCount: { value: 0 },
    rois: { value: Array.from({ length: MAX_ROIS }, () => new THREE.Vector4()) }, // x0, y0, x1, y1 metres, tileset frame
  };
}

const vertexShader = /* glsl */ `
uniform mat4 toTileset;
varying vec2 vUv;
varying vec3 vNormal;
varying vec3 vTileset;
void main() {
  vUv = uv;
  vNormal = normalize(normalMatrix * normal);
  vec4 world = modelMatrix * vec4(position, 1.0);
  vTileset = (toTileset * world).xyz;
  gl_Position = projectionMatrix * viewMatrix * world;
}`;

const rampGlsl = RAMP.map((c) => `vec3(${c.map((v) => (v ** 2.2).toFixed(4)).join(", ")})`).join(", ");

const fragmentShader = /* glsl */ `
uniform sampler2D map;
uniform float hasMap;
uniform float zoomKind;
uniform float isWall;
uniform int colouring;
uniform vec2 heightRange;
uniform vec3 lightDirection;
uniform float lighting;
uniform float ambient;
uniform int shadeZoom;
uniform int showWalls;
uniform int showRois;
uniform int roiCount;
uniform vec4 rois[${MAX_ROIS}];
varying vec2 vUv;
varying vec3 vNormal;
varying vec3 vTileset;
const vec3 stops[${RAMP.length}] = vec3[](${rampGlsl});
vec3 ramp(float t) {
  float x = clamp(t, 0.0, 1.0) * float(${RAMP.length - 1});
  int i = min(int(x), ${RAMP.length - 2});
  return mix(stops[i], stops[i + 1], x - float(i));
}
void main() {
  if (isWall > 0.5 && showWalls == 0) discard;
  vec3 base;
  if (isWall > 0.5) {
    // Hatched grey: nothing was measured here, the triangle only bridges a jump.
    base = mix(vec3(0.015), vec3(0.05), step(0.5, fract((gl_FragCoord.x + gl_FragCoord.y) / 10.0)));
  } else if (colouring == 1) {
    base = ramp((vTileset.z - heightRange.x) / max(heightRange.y - heightRange.x, 1e-12));
  } else {
    base = hasMap > 0.5 ? texture2D(map, vUv).rgb : vec3(0.2);
  }
  if (shadeZoom == 1 && isWall < 0.5) base *= zoomKind > 1.5 ? vec3(1.0, 0.55, 0.3) : vec3(0.45, 1.0, 0.45);
  vec3 normal = normalize(vNormal);
  if (!gl_FrontFacing) normal = -normal;
  vec3 light = normalize((viewMatrix * vec4(lightDirection, 0.0)).xyz);
  vec3 up = normalize((viewMatrix * vec4(0.0, 0.0, 1.0, 0.0)).xyz);
  // Lambert through the normal scaled to unit height, (-dz/dx, -dz/dy, 1): linear in the slopes,
  // so a coarse tile shades as the mean of the finer tiles it stands for, and levels of detail
  // side by side match in brightness (unit normals darken rough, fine tiles). Clamped
  // symmetrically about a flat facet's value, which keeps that mean for slopes within range.
  float facing = dot(normal, up);
  float flatLit = max(dot(light, up), 0.0);
  float direct = facing > 0.05 ? clamp(dot(normal, light) / facing, 0.0, 2.0 * flatLit) : max(dot(normal, light), 0.0);
  float lit = ambient + (1.0 - ambient) * direct;
  vec3 colour = base * mix(1.0, lit, isWall > 0.5 ? 0.0 : lighting);
  if (showRois == 1) {
    vec2 p = vTileset.xy;
    vec2 width = fwidth(p) * 1.5;
    for (int i = 0; i < ${MAX_ROIS}; i++) {
      if (i >= roiCount) break;
      vec4 r = rois[i];
      bool alongX = p.x > r.x - width.x && p.x < r.z + width.x;
      bool alongY = p.y > r.y - width.y && p.y < r.w + width.y;
      bool onVertical = min(abs(p.x - r.x), abs(p.x - r.z)) < width.x && alongY;
      bool onHorizontal = min(abs(p.y - r.y), abs(p.y - r.w)) < width.y && alongX;
      if (onVertical || onHorizontal) colour = vec3(1.0, 0.65, 0.03);
    }
  }
  gl_FragColor = vec4(colour, 1.0);
  #include <colorspace_fragment>
}`;

// The material of one tile mesh, from the one the glTF loader made (its texture is kept).
export function surfaceMaterial(loaded, zoom, shared) {
  const isWall = loaded.name === "wall";
  return new THREE.ShaderMaterial({
    uniforms: {
      ...shared,
      map: { value: loaded.map ?? null },
      hasMap: { value: loaded.map ? 1 : 0 },
      zoomKind: { value: ZOOM_KINDS[zoom] ?? 0 },
      isWall: { value: isWall ? 1 : 0 },
    },
    vertexShader,
    fragmentShader,
    side: THREE.DoubleSide,
  });
}

export function isWallMesh(mesh) {
  return mesh.material?.uniforms?.isWall?.value === 1;
}

// The ramp as a CSS gradient from the bottom (low) to the top (high).
export function rampGradient() {
  const stops = RAMP.map((c, i) => `rgb(${c.map((v) => Math.round(v * 255)).join(",")}) ${(100 * i) / (RAMP.length - 1)}%`);
  return `linear-gradient(to top, ${stops.join(", ")})`;
}

// Direction towards a light at `azimuthDeg` (clockwise from the image's up, as on a map) and
// `elevationDeg` above the surface, in the tileset frame (x right, y up the image, z height).
export function lightDirection(azimuthDeg, elevationDeg, target) {
  const azimuth = THREE.MathUtils.degToRad(azimuthDeg);
  const elevation = THREE.MathUtils.degToRad(elevationDeg);
  return target.set(Math.cos(elevation) * Math.sin(azimuth), Math.cos(elevation) * Math.cos(azimuth), Math.sin(elevation));
}
