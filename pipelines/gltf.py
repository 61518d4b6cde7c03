"""A predicted object as one glTF 2.0 binary (``.glb``) that Blender, three.js or any glTF viewer opens textured.

The file holds the mesh (positions, smooth normals, the template's UVs: vertices split along its seam), the albedo
as an embedded PNG (``baseColorTexture``) and a metallic-roughness material whose ``roughnessFactor`` and
``metallicFactor`` are the predicted ones (the project's roughness is Blender's: the GGX alpha is its square, as
in glTF); the predicted specular level has no core glTF field and rides in the material's ``extras``. glTF is
+Y up and the project's world +Z up: positions and normals are turned (x, y, z) -> (x, z, -y), which Blender's
importer turns back. Written with numpy, struct and json only, atomically.
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from dibrpp.io import atomic_path

FLOAT, UINT32 = 5126, 5125  # accessor component types
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
LINEAR, LINEAR_MIPMAP_LINEAR, REPEAT, CLAMP_TO_EDGE = 9729, 9987, 10497, 33071
JSON_CHUNK, BIN_CHUNK = 0x4E4F534A, 0x004E4942
Z_UP_TO_Y_UP = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], np.float32)  # (x, y, z) -> (x, z, -y)


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit area-weighted vertex normals of a triangle mesh (up where a vertex has no face)."""
    a, b, c = (verts[faces[:, i]] for i in range(3))
    face_normals = np.cross(b - a, c - a)
    normals = np.zeros_like(verts)
    for i in range(3):
        np.add.at(normals, faces[:, i], face_normals)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    return np.where(length > 0, normals / np.maximum(length, 1e-30), np.array([0, 0, 1], verts.dtype))


def write_glb(path, verts, faces, uvs, texture_png: bytes, roughness: float, metallic: float,
              extras: dict | None = None, name: str = "prediction") -> Path:
    """Write ``path``: triangles ``faces`` (F, 3) over ``verts`` (V, 3, world +Z up) with per-vertex ``uvs`` (V, 2;
    OBJ's convention, v up from the image's bottom row), textured by ``texture_png`` (a PNG file's bytes)."""
    verts = np.ascontiguousarray(verts, np.float32)
    faces = np.ascontiguousarray(faces, np.int64)
    uvs = np.ascontiguousarray(uvs, np.float32)
    if verts.ndim != 2 or verts.shape[1] != 3 or uvs.shape != (len(verts), 2) or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"expected verts (V, 3), uvs (V, 2) and faces (F, 3); got {verts.shape}, {uvs.shape}, "
                         f"{faces.shape}")
    if len(faces) == 0 or faces.min() < 0 or faces.max() >= len(verts):
        raise ValueError(f"faces index vertices {faces.min(initial=0)}..{faces.max(initial=0)} of {len(verts)}")
    if not texture_png.startswith(b"\x89PNG\r\n\x1a\n"):
        raise ValueError("texture_png is not a PNG file's bytes")
    positions = verts @ Z_UP_TO_Y_UP.T
    normals = vertex_normals(verts, faces) @ Z_UP_TO_Y_UP.T
    texcoords = np.stack([uvs[:, 0], 1.0 - uvs[:, 1]], -1)  # glTF's v runs down from the image's top row
    blobs = [positions.astype(np.float32).tobytes(), normals.astype(np.float32).tobytes(),
             texcoords.astype(np.float32).tobytes(), faces.astype(np.uint32).tobytes(), texture_png]
    views, binary = [], b""
    for i, blob in enumerate(blobs):
        view = {"buffer": 0, "byteOffset": len(binary), "byteLength": len(blob)}
        if i < 3:
            view["target"] = ARRAY_BUFFER
        elif i == 3:
            view["target"] = ELEMENT_ARRAY_BUFFER
        views.append(view)
        binary += blob + b"\0" * (-len(blob) % 4)
    count = len(verts)
    accessors = [
        {"bufferView": 0, "componentType": FLOAT, "count": count, "type": "VEC3",
         "min": positions.min(0).tolist(), "max": positions.max(0).tolist()},
        {"bufferView": 1, "componentType": FLOAT, "count": count, "type": "VEC3"},
        {"bufferView": 2, "componentType": FLOAT, "count": count, "type": "VEC2"},
        {"bufferView": 3, "componentType": UINT32, "count": int(faces.size), "type": "SCALAR"},
    ]
    material = {"name": f"{name} material",
                "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                                         "metallicFactor": float(np.clip(metallic, 0, 1)),
                                         "roughnessFactor": float(np.clip(roughness, 0, 1))}}
    if extras:
        material["extras"] = extras
    document = {
        "asset": {"version": "2.0", "generator": "dibrpp pipelines.predict"},
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": name}],
        "meshes": [{"name": name, "primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
                                                 "indices": 3, "material": 0, "mode": 4}]}],
        "materials": [material],
        "textures": [{"source": 0, "sampler": 0}],
        "samplers": [{"magFilter": LINEAR, "minFilter": LINEAR_MIPMAP_LINEAR, "wrapS": REPEAT, "wrapT": CLAMP_TO_EDGE}],
        "images": [{"bufferView": 4, "mimeType": "image/png", "name": "albedo"}],
        "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": len(binary)}],
    }
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), JSON_CHUNK) + text + struct.pack("<II", len(binary), BIN_CHUNK) + binary
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)
    return path
