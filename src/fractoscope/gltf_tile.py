"""One textured triangle mesh as a glTF 2.0 binary (GLB), written with pygltflib.

Positions are metres, +Y up (glTF's convention): X along image columns, Y the height, Z along
image rows (down the image), which keeps the SEM image unmirrored seen from above.
"""

from __future__ import annotations

import cv2
import numpy as np
import pygltflib

METRES_PER_UM = 1e-6


def to_gltf_positions_m(
    positions: np.ndarray, *, pixel_size_um: float, origin_um: tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """(col_px, row_px, z_um) to glTF metres: X = columns, Y = height (up), Z = rows; pixel (0, 0)
    lands at `origin_um` (x, y)."""
    x_um = origin_um[0] + positions[:, 0] * pixel_size_um
    y_um = origin_um[1] + positions[:, 1] * pixel_size_um
    return np.column_stack([x_um, positions[:, 2], y_um]) * METRES_PER_UM


def tile_glb(tile, *, pixel_size_um: float, origin_um: tuple[float, float] = (0.0, 0.0), extras: dict | None = None) -> bytes:
    """A `surface_mesh.MeshTile` as GLB, its texture as JPEG; pixel (0, 0) at `origin_um` (x, y)."""
    return mesh_glb(
        to_gltf_positions_m(tile.positions, pixel_size_um=pixel_size_um, origin_um=origin_um),
        tile.normals,
        tile.uvs,
        tile.triangles,
        encode_texture(tile.texture),
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
    extras: dict | None = None,
) -> bytes:
    """A GLB holding one mesh: positions (N, 3) metres, unit normals (N, 3), texture coordinates
    (N, 2) with (0, 0) at the image's top-left, triangles (M, 3) counter-clockwise seen from +Y,
    and the JPEG texture. `extras` lands on the mesh node (glTF extras)."""
    positions = np.ascontiguousarray(positions_m, np.float32)
    # 16-bit indices when they stay below 65535, which glTF reserves for primitive restart.
    index_type, index_component = (np.uint16, pygltflib.UNSIGNED_SHORT) if len(positions) <= 65535 else (np.uint32, pygltflib.UNSIGNED_INT)
    arrays = [
        (np.ascontiguousarray(triangles, index_type).ravel(), pygltflib.ELEMENT_ARRAY_BUFFER),
        (positions, pygltflib.ARRAY_BUFFER),
        (np.ascontiguousarray(normals, np.float32), pygltflib.ARRAY_BUFFER),
        (np.ascontiguousarray(uvs, np.float32), pygltflib.ARRAY_BUFFER),
    ]
    parts, views, offset = [], [], 0
    for values, target in arrays:
        views.append(pygltflib.BufferView(buffer=0, byteOffset=offset, byteLength=values.nbytes, target=target))
        padding = -values.nbytes % 4
        parts += [values.tobytes(), b"\0" * padding]
        offset += values.nbytes + padding
    image_view = len(views)
    views.append(pygltflib.BufferView(buffer=0, byteOffset=offset, byteLength=len(texture_jpeg)))
    parts += [texture_jpeg, b"\0" * (-len(texture_jpeg) % 4)]
    blob = b"".join(parts)

    accessors = [
        pygltflib.Accessor(bufferView=0, componentType=index_component, count=int(triangles.size), type=pygltflib.SCALAR),
        pygltflib.Accessor(
            bufferView=1, componentType=pygltflib.FLOAT, count=len(positions), type=pygltflib.VEC3,
            min=positions.min(axis=0).tolist(), max=positions.max(axis=0).tolist(),
        ),
        pygltflib.Accessor(bufferView=2, componentType=pygltflib.FLOAT, count=len(positions), type=pygltflib.VEC3),
        pygltflib.Accessor(bufferView=3, componentType=pygltflib.FLOAT, count=len(positions), type=pygltflib.VEC2),
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
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[pygltflib.Node(mesh=0, extras=extras or {})],
        meshes=[pygltflib.Mesh(primitives=[primitive])],
        materials=[material],
        textures=[pygltflib.Texture(source=0, sampler=0)],
        samplers=[pygltflib.Sampler(magFilter=pygltflib.LINEAR, minFilter=pygltflib.LINEAR, wrapS=pygltflib.CLAMP_TO_EDGE, wrapT=pygltflib.CLAMP_TO_EDGE)],
        images=[pygltflib.Image(bufferView=image_view, mimeType="image/jpeg")],
        accessors=accessors,
        bufferViews=views,
        buffers=[pygltflib.Buffer(byteLength=len(blob))],
    )
    gltf.set_binary_blob(blob)
    return b"".join(gltf.save_to_bytes())
