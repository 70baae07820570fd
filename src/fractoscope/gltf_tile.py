"""One textured triangle mesh as a compact glTF 2.0 binary (GLB), written with pygltflib.

Positions are metres, +Y up (glTF's convention): X along image columns, Y the height, Z along
image rows (down the image), which keeps the SEM image unmirrored seen from above.

Geometry is quantized (KHR_mesh_quantization: 16-bit positions on a `PositionGrid` that the node's
translation and scale turn back into metres, 8-bit normals, 16-bit texture coordinates) and then
compressed with meshoptimizer (EXT_meshopt_compression), which every three.js-based 3D Tiles
client decodes: a tile is about a fifth of its float32 size.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import meshoptimizer
import numpy as np
import pygltflib

METRES_PER_UM = 1e-6
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
        q = np.rint((np.asarray(positions_m, np.float64) - self.origin_m) / self.step_m)
        return np.clip(q, 0, POSITION_LEVELS).astype(np.uint16)


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
    grid: PositionGrid,
    origin_um: tuple[float, float] = (0.0, 0.0),
    extras: dict | None = None,
) -> bytes:
    """A `surface_mesh.MeshTile` as GLB on `grid`, its texture as JPEG; pixel (0, 0) at
    `origin_um` (x, y)."""
    return mesh_glb(
        to_gltf_positions_m(tile.positions, pixel_size_um=pixel_size_um, origin_um=origin_um),
        tile.normals,
        tile.uvs,
        tile.triangles,
        encode_texture(tile.texture),
        grid=grid,
        extras=extras,
    )


def encode_texture(grey: np.ndarray, *, jpeg_quality: int = 90) -> bytes:
    """(rows, cols) uint8 or uint16 grey image as JPEG bytes."""
    if grey.dtype != np.uint8:
        grey = cv2.convertScaleAbs(grey, alpha=255.0 / max(float(grey.max()), 1.0))
    ok, encoded = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return encoded.tobytes()


def mesh_glb(
    positions_m: np.ndarray,
    normals: np.ndarray,
    uvs: np.ndarray,
    triangles: np.ndarray,
    texture_jpeg: bytes,
    *,
    grid: PositionGrid,
    extras: dict | None = None,
) -> bytes:
    """A GLB holding one mesh: positions (N, 3) metres (quantized to `grid`), unit normals (N, 3),
    texture coordinates (N, 2) in [0, 1] with (0, 0) at the image's top-left, triangles (M, 3)
    counter-clockwise seen from +Y, and the JPEG texture. `extras` lands on the mesh node."""
    count = len(positions_m)
    quantized = np.zeros((count, 4), np.uint16)  # x, y, z and the padding to 4-byte vertices
    quantized[:, :3] = grid.quantize(positions_m)
    normals_i8 = np.zeros((count, 4), np.int8)
    normals_i8[:, :3] = np.rint(np.clip(normals, -1.0, 1.0) * 127)
    uvs_u16 = np.rint(np.clip(uvs, 0.0, 1.0) * 65535).astype(np.uint16)
    indices = np.ascontiguousarray(triangles, np.uint32).ravel()
    # 16-bit indices when they stay below 65535, which glTF reserves for primitive restart.
    index_size, index_component = (2, pygltflib.UNSIGNED_SHORT) if count <= 65535 else (4, pygltflib.UNSIGNED_INT)

    meshoptimizer.encode_vertex_version(0)  # the version EXT_meshopt_compression specifies
    streams = [  # (compressed bytes, byte length when decoded, stride, element count, mode, target)
        (meshoptimizer.encode_index_buffer(indices, len(indices), count), indices.size * index_size, index_size,
         indices.size, "TRIANGLES", pygltflib.ELEMENT_ARRAY_BUFFER),
    ] + [
        (meshoptimizer.encode_vertex_buffer(values), values.nbytes, values.strides[0], count, "ATTRIBUTES", pygltflib.ARRAY_BUFFER)
        for values in (quantized, normals_i8, uvs_u16)
    ]
    parts, views, compressed_offset, decoded_offset = [], [], 0, 0
    for compressed, decoded_length, stride, elements, mode, target in streams:
        views.append(pygltflib.BufferView(
            buffer=1, byteOffset=decoded_offset, byteLength=decoded_length, target=target,
            byteStride=stride if mode == "ATTRIBUTES" else None,
            extensions={MESHOPT: {"buffer": 0, "byteOffset": compressed_offset, "byteLength": len(compressed),
                                  "byteStride": stride, "count": elements, "mode": mode}},
        ))
        parts += [compressed, b"\0" * (-len(compressed) % 4)]
        compressed_offset += len(compressed) + -len(compressed) % 4
        decoded_offset += decoded_length + -decoded_length % 4
    image_view = len(views)
    views.append(pygltflib.BufferView(buffer=0, byteOffset=compressed_offset, byteLength=len(texture_jpeg)))
    parts += [texture_jpeg, b"\0" * (-len(texture_jpeg) % 4)]
    blob = b"".join(parts)

    accessors = [
        pygltflib.Accessor(bufferView=0, componentType=index_component, count=int(indices.size), type=pygltflib.SCALAR),
        pygltflib.Accessor(
            bufferView=1, componentType=pygltflib.UNSIGNED_SHORT, count=count, type=pygltflib.VEC3,
            min=quantized[:, :3].min(axis=0).tolist(), max=quantized[:, :3].max(axis=0).tolist(),
        ),
        pygltflib.Accessor(bufferView=2, componentType=pygltflib.BYTE, normalized=True, count=count, type=pygltflib.VEC3),
        pygltflib.Accessor(bufferView=3, componentType=pygltflib.UNSIGNED_SHORT, normalized=True, count=count, type=pygltflib.VEC2),
    ]
    primitive = pygltflib.Primitive(
        attributes=pygltflib.Attributes(POSITION=1, NORMAL=2, TEXCOORD_0=3), indices=0, material=0, mode=pygltflib.TRIANGLES
    )
    material = pygltflib.Material(
        pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
            baseColorTexture=pygltflib.TextureInfo(index=0), metallicFactor=0.0, roughnessFactor=1.0
        ),
        doubleSided=True,
    )
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="fractoscope"),
        extensionsUsed=[MESHOPT, QUANTIZATION],
        extensionsRequired=[MESHOPT, QUANTIZATION],
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[pygltflib.Node(mesh=0, translation=list(grid.origin_m), scale=list(grid.step_m), extras=extras or {})],
        meshes=[pygltflib.Mesh(primitives=[primitive])],
        materials=[material],
        textures=[pygltflib.Texture(source=0, sampler=0)],
        samplers=[pygltflib.Sampler(magFilter=pygltflib.LINEAR, minFilter=pygltflib.LINEAR, wrapS=pygltflib.CLAMP_TO_EDGE, wrapT=pygltflib.CLAMP_TO_EDGE)],
        images=[pygltflib.Image(bufferView=image_view, mimeType="image/jpeg")],
        accessors=accessors,
        bufferViews=views,
        # Buffer 1 holds no bytes: it is where the decoder writes the decompressed views.
        buffers=[pygltflib.Buffer(byteLength=len(blob)), pygltflib.Buffer(byteLength=decoded_offset, extensions={MESHOPT: {"fallback": True}})],
    )
    return _glb(gltf, blob)


def _glb(gltf: pygltflib.GLTF2, blob: bytes) -> bytes:
    """The GLB container of a document and its BIN chunk (buffer 0). pygltflib's own writer merges
    every buffer into the BIN chunk, which would give the fallback buffer bytes it must not have."""
    document = gltf.gltf_to_json(separators=(",", ":"), indent=None).encode("utf-8")
    document += b" " * (-len(document) % 4)
    blob += b"\0" * (-len(blob) % 4)
    length = 12 + 8 + len(document) + 8 + len(blob)
    return b"".join([
        pygltflib.MAGIC, struct.pack("<II", pygltflib.GLTF_VERSION, length),
        struct.pack("<I", len(document)), pygltflib.JSON.encode(), document,
        struct.pack("<I", len(blob)), pygltflib.BIN.encode(), blob,
    ])
