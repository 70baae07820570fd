"""One textured triangle mesh as a compact glTF 2.0 binary (GLB), written with pygltflib.

Positions are metres, +Y up (glTF's convention): X along image columns, Y the height, Z along
image rows (down the image), which keeps the SEM image unmirrored seen from above.

Geometry is quantized (KHR_mesh_quantization: 16-bit positions on a `PositionGrid` that the node's
translation and scale turn back into metres, 8-bit normals, 16-bit texture coordinates) and then
compressed with meshoptimizer (EXT_meshopt_compression), which every three.js-based 3D Tiles
client decodes: a tile is about a fifth of its float32 size. Without a grid the geometry is
plain float32, for tools that lack a meshopt decoder.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import meshoptimizer
import numpy as np
import pygltflib

from fractoscope.units import METRES_PER_UM

POSITION_LEVELS = 65535  # 16-bit unsigned positions
MESHOPT = "EXT_meshopt_compression"
QUANTIZATION = "KHR_mesh_quantization"


@dataclass(frozen=True)
class PositionGrid:
    """The grid positions are quantized to: metres = origin_m + q * step_m per axis, q in 0..65535.
    All tiles of one mesh share one grid, so a border vertex that two tiles share stays identical."""

    origin_m: tuple[float, float, float]
    step_m: tuple[float, float, float]

    @classmethod
    def spanning(cls, low_m, high_m) -> PositionGrid:
        """The finest grid covering the box [low_m, high_m] (glTF metres, per axis)."""
        low = np.asarray(low_m, np.float64)
        extent = np.maximum(np.asarray(high_m, np.float64) - low, 1e-12)
        return cls(tuple(low.tolist()), tuple((extent / POSITION_LEVELS).tolist()))

    def quantize(self, positions_m: np.ndarray) -> np.ndarray:
        """(N, 3) metres to (N, 3) grid indices (uint16)."""
        q = np.subtract(positions_m, self.origin_m, dtype=np.float64)
        q /= self.step_m
        np.rint(q, out=q)
        return np.clip(q, 0, POSITION_LEVELS, out=q).astype(np.uint16)


def to_gltf_positions_m(
    positions: np.ndarray, *, pixel_size_um: float, origin_um: tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """(col_px, row_px, z_um) to glTF metres: X = columns, Y = height (up), Z = rows; pixel (0, 0)
    lands at `origin_um` (x, y)."""
    x_um = origin_um[0] + positions[:, 0] * pixel_size_um
    y_um = origin_um[1] + positions[:, 1] * pixel_size_um
    return np.column_stack([x_um, positions[:, 2], y_um]) * METRES_PER_UM


def tile_glb(
    tile,
    *,
    pixel_size_um: float,
    grid: PositionGrid | None,
    origin_um: tuple[float, float] = (0.0, 0.0),
    extras: dict | None = None,
) -> bytes:
    """A `mesh.levels.LodTile` as GLB, compact on `grid` (None: plain float32), its texture as
    PNG; pixel (0, 0) at `origin_um` (x, y); its walls and its floor (if any) as primitives of
    their own."""
    return mesh_glb(
        to_gltf_positions_m(tile.positions, pixel_size_um=pixel_size_um, origin_um=origin_um),
        tile.normals,
        tile.uvs,
        tile.triangles[~tile.walls],
        encode_texture(tile.texture),
        grid=grid,
        extras=extras,
        wall_triangles=tile.triangles[tile.walls],
        floor_triangles=tile.floor,
    )


def encode_texture(grey: np.ndarray) -> bytes:
    """(rows, cols) uint8 grey image as PNG bytes. Lossless: tiles meshed apart show their shared
    border with the same grey values (JPEG's blocks made them differ by up to 16 grey levels), at
    about 1 KB more per 65 x 65 texture."""
    ok, encoded = cv2.imencode(".png", np.asarray(grey, np.uint8), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return encoded.tobytes()


_COMPONENT_TYPES = {
    np.dtype(np.float32): pygltflib.FLOAT,
    np.dtype(np.uint16): pygltflib.UNSIGNED_SHORT,
    np.dtype(np.int8): pygltflib.BYTE,
    np.dtype(np.uint32): pygltflib.UNSIGNED_INT,
}


def mesh_glb(
    positions_m: np.ndarray,
    normals: np.ndarray,
    uvs: np.ndarray,
    triangles: np.ndarray,
    texture_png: bytes,
    *,
    grid: PositionGrid | None,
    extras: dict | None = None,
    wall_triangles: np.ndarray | None = None,
    floor_triangles: np.ndarray | None = None,
) -> bytes:
    """A GLB holding one mesh: positions (N, 3) metres, unit normals (N, 3), texture coordinates
    (N, 2) in [0, 1] with (0, 0) at the image's top-left, triangles (M, 3) counter-clockwise seen
    from +Y, and the PNG texture. `wall_triangles` (K, 3), on the same vertices, become a second
    primitive with the material named "wall" (see mesh.walls), so that viewers can show them
    differently; `floor_triangles` a third, material "unmeasured" (flat grey, mesh.outline). With
    a `grid` the geometry is quantized to it and meshopt-compressed; without, it is plain float32
    with no extensions, which any glTF reader opens. `extras` lands on the mesh node."""
    count = len(positions_m)
    index_sets = _index_sets(triangles, wall_triangles, floor_triangles, count)
    attributes = _vertex_attributes(positions_m, normals, uvs, grid)
    geometry = _GeometryBuffers.of(
        [indices for indices, _ in index_sets], attributes, count, compressed=grid is not None
    )
    image_view = len(geometry.views)
    views = geometry.views + [pygltflib.BufferView(buffer=0, byteOffset=geometry.size, byteLength=len(texture_png))]
    blob = b"".join(geometry.parts + [texture_png, b"\0" * (-len(texture_png) % 4)])
    buffers = [pygltflib.Buffer(byteLength=len(blob))]
    node = pygltflib.Node(mesh=0, extras=extras or {})
    extensions = []
    if grid is not None:
        buffers.append(pygltflib.Buffer(byteLength=geometry.decoded_size, extensions={MESHOPT: {"fallback": True}}))
        node.translation, node.scale = list(grid.origin_m), list(grid.step_m)
        extensions = [MESHOPT, QUANTIZATION]
    primitives = _primitives([material for _, material in index_sets])
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="fractoscope"),
        extensionsUsed=extensions,
        extensionsRequired=extensions,
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[node],
        meshes=[pygltflib.Mesh(primitives=primitives)],
        materials=[_MATERIAL, _WALL_MATERIAL, _FLOOR_MATERIAL],
        textures=[pygltflib.Texture(source=0, sampler=0)],
        samplers=[_sampler()],
        images=[pygltflib.Image(bufferView=image_view, mimeType="image/png")],
        accessors=_accessors([indices for indices, _ in index_sets], attributes, count, normalized=grid is not None),
        bufferViews=views,
        buffers=buffers,
    )
    return _glb(gltf, blob)


def _index_sets(triangles, wall_triangles, floor_triangles, count: int) -> list[tuple[np.ndarray, int]]:
    """(flat indices, material) of each primitive that has triangles: the surface's (material 0),
    the walls' (material 1), then the floor's (material 2; None: none), for `count` vertices."""
    # 16-bit indices when they stay below 65535, which glTF reserves for primitive restart.
    index_type = np.uint16 if count <= 65535 else np.uint32
    none = np.zeros((0, 3))
    parts = [(triangles, 0), (none if wall_triangles is None else wall_triangles, 1)]
    parts.append((none if floor_triangles is None else floor_triangles, 2))
    return [(np.ascontiguousarray(t, index_type).ravel(), material) for t, material in parts if len(t)]


def _primitives(materials: list[int]) -> list[pygltflib.Primitive]:
    """One triangle primitive per index buffer, with its material."""
    # Accessors 0 to 2 are the vertex attributes, then one index accessor per primitive.
    return [
        pygltflib.Primitive(
            attributes=pygltflib.Attributes(POSITION=0, NORMAL=1, TEXCOORD_0=2),
            indices=3 + k,
            material=material,
            mode=pygltflib.TRIANGLES,
        )
        for k, material in enumerate(materials)
    ]


def _sampler() -> pygltflib.Sampler:
    """Linear filtering; texture coordinates clamped to the edge."""
    return pygltflib.Sampler(
        magFilter=pygltflib.LINEAR,
        minFilter=pygltflib.LINEAR,
        wrapS=pygltflib.CLAMP_TO_EDGE,
        wrapT=pygltflib.CLAMP_TO_EDGE,
    )


_MATERIAL = pygltflib.Material(
    name="surface",
    pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
        baseColorTexture=pygltflib.TextureInfo(index=0), metallicFactor=0.0, roughnessFactor=1.0
    ),
    doubleSided=True,
)
# Walls bridge a jump nothing measured: plain grey, so that a viewer that knows nothing of them
# still tells them from the textured surface.
_WALL_MATERIAL = pygltflib.Material(
    name="wall",
    pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
        baseColorFactor=[0.45, 0.45, 0.45, 1.0], metallicFactor=0.0, roughnessFactor=1.0
    ),
    doubleSided=True,
)
# Where nothing was measured, asked for as a floor at height zero: plain light grey, no relief.
_FLOOR_MATERIAL = pygltflib.Material(
    name="unmeasured",
    pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
        baseColorFactor=[0.7, 0.7, 0.7, 1.0], metallicFactor=0.0, roughnessFactor=1.0
    ),
    doubleSided=True,
)


def _vertex_attributes(positions_m, normals, uvs, grid: PositionGrid | None) -> list[np.ndarray]:
    """Positions, normals and texture coordinates as stored: float32, or on `grid` 16-bit
    positions and texture coordinates and 8-bit normals (positions and normals padded to 4-byte
    vertices, as meshopt's codec wants)."""
    if grid is None:
        return [np.ascontiguousarray(values, np.float32) for values in (positions_m, normals, uvs)]
    count = len(positions_m)
    quantized = np.zeros((count, 4), np.uint16)  # x, y, z and the padding to 4-byte vertices
    quantized[:, :3] = grid.quantize(positions_m)
    normals_i8 = np.zeros((count, 4), np.int8)
    normals_i8[:, :3] = np.rint(np.clip(normals, -1.0, 1.0) * 127)
    uvs_u16 = np.rint(np.clip(uvs, 0.0, 1.0) * 65535).astype(np.uint16)
    meshoptimizer.encode_vertex_version(0)  # the version EXT_meshopt_compression specifies
    return [quantized, normals_i8, uvs_u16]


@dataclass(frozen=True)
class _GeometryBuffers:
    """Buffer views (the attributes, then the index buffers) and their bytes in buffer 0
    (`parts`, each padded to 4 bytes, `size` in all); compressed views decode into buffer 1, of
    `decoded_size` bytes."""

    views: list
    parts: list[bytes]
    size: int
    decoded_size: int

    @classmethod
    def of(
        cls, index_sets: list[np.ndarray], attributes: list[np.ndarray], count: int, *, compressed: bool
    ) -> _GeometryBuffers:
        parts, views, offset, decoded_offset = [], [], 0, 0
        for values, target in [(a, pygltflib.ARRAY_BUFFER) for a in attributes] + [
            (i, pygltflib.ELEMENT_ARRAY_BUFFER) for i in index_sets
        ]:
            if not compressed:
                data = values.tobytes()
                views.append(pygltflib.BufferView(buffer=0, byteOffset=offset, byteLength=len(data), target=target))
            else:
                if target == pygltflib.ELEMENT_ARRAY_BUFFER:
                    data = meshoptimizer.encode_index_buffer(values.astype(np.uint32), values.size, count)
                    stride, elements, mode = values.itemsize, values.size, "TRIANGLES"
                else:
                    data = meshoptimizer.encode_vertex_buffer(values)
                    stride, elements, mode = values.strides[0], count, "ATTRIBUTES"
                # The view itself lies in the data-less buffer 1, where the decoder writes it.
                views.append(
                    pygltflib.BufferView(
                        buffer=1,
                        byteOffset=decoded_offset,
                        byteLength=values.nbytes,
                        target=target,
                        byteStride=stride if mode == "ATTRIBUTES" else None,
                        extensions={
                            MESHOPT: {
                                "buffer": 0,
                                "byteOffset": offset,
                                "byteLength": len(data),
                                "byteStride": stride,
                                "count": elements,
                                "mode": mode,
                            }
                        },
                    )
                )
                decoded_offset += values.nbytes + -values.nbytes % 4
            parts += [data, b"\0" * (-len(data) % 4)]
            offset += len(data) + -len(data) % 4
        return cls(views, parts, offset, decoded_offset)


def _accessors(index_sets: list[np.ndarray], attributes: list[np.ndarray], count: int, *, normalized: bool) -> list:
    """Accessors of the three attributes, then of each index buffer; integer normals and texture
    coordinates (`normalized`) stand for [-1, 1] and [0, 1]."""
    axes = [attributes[0][:, axis] for axis in range(3)]  # one column at a time: 17x quicker than axis=0
    low, high = [values.min().item() for values in axes], [values.max().item() for values in axes]
    return [
        pygltflib.Accessor(
            bufferView=0,
            componentType=_COMPONENT_TYPES[attributes[0].dtype],
            count=count,
            type=pygltflib.VEC3,
            min=low,
            max=high,
        ),
        pygltflib.Accessor(
            bufferView=1,
            componentType=_COMPONENT_TYPES[attributes[1].dtype],
            normalized=normalized or None,
            count=count,
            type=pygltflib.VEC3,
        ),
        pygltflib.Accessor(
            bufferView=2,
            componentType=_COMPONENT_TYPES[attributes[2].dtype],
            normalized=normalized or None,
            count=count,
            type=pygltflib.VEC2,
        ),
    ] + [
        pygltflib.Accessor(
            bufferView=3 + k,
            componentType=_COMPONENT_TYPES[indices.dtype],
            count=int(indices.size),
            type=pygltflib.SCALAR,
        )
        for k, indices in enumerate(index_sets)
    ]


def _glb(gltf: pygltflib.GLTF2, blob: bytes) -> bytes:
    """The GLB container of a document and its BIN chunk (buffer 0). pygltflib's own writer merges
    every buffer into the BIN chunk, which would give meshopt's fallback buffer bytes it must not
    have."""
    document = gltf.gltf_to_json(separators=(",", ":"), indent=None).encode("utf-8")
    document += b" " * (-len(document) % 4)
    blob += b"\0" * (-len(blob) % 4)
    length = 12 + 8 + len(document) + 8 + len(blob)
    return b"".join(
        [
            pygltflib.MAGIC,
            struct.pack("<II", pygltflib.GLTF_VERSION, length),
            struct.pack("<I", len(document)),
            pygltflib.JSON.encode(),
            document,
            struct.pack("<I", len(blob)),
            pygltflib.BIN.encode(),
            blob,
        ]
    )
