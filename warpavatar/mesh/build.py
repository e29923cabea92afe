"""The mesh export's stages in order: a fitted avatar in, a textured, skinned :class:`AvatarMesh` out.

renders of the canonical avatar (:func:`~warpavatar.mesh.views.render_canonical_views`, the Gaussians blurred as
at the fit's resolution where the fit recorded it: :func:`recorded_pixel_size`) -> a closed surface fused from them
(:func:`~warpavatar.mesh.surface.extract_surface`) -> the surface fitted to the Gaussians' silhouettes in frames of
the training motion, where the fit recorded one (:func:`fit_posed_silhouettes`) -> UVs
(:func:`~warpavatar.mesh.texture.unwrap`) -> normals -> texture atlas and vertex colours baked from the renders
(:mod:`warpavatar.mesh.texture`) -> skin weights (:func:`~warpavatar.mesh.skin.skin_mesh`, blended from the Gaussians
around each vertex). A static format skips what it cannot hold (``texture``, ``vertex_colors``, ``skin`` off). The
motion is applied afterwards, by :func:`~warpavatar.mesh.skin.mesh_animation`.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from warpavatar.mesh.mesh_data import AvatarMesh

__all__ = ["DEFAULT_TRIANGLES", "DEFAULT_TEXTURE_SIZE", "DEFAULT_VIEW_COUNT", "DEFAULT_VIEW_SIZE",
           "recorded_pixel_size", "recorded_training_motion", "fit_posed_silhouettes", "build_avatar_mesh"]

DEFAULT_TRIANGLES = 50_000
"""Triangles of the exported mesh, after decimation."""

DEFAULT_TEXTURE_SIZE = 1024
"""Width and height of the texture atlas [px]."""

DEFAULT_VIEW_COUNT = 48
"""Renders of the canonical avatar the surface is fused from and the texture baked from."""

DEFAULT_VIEW_SIZE = 256
"""Width and height of each render [px]."""


def recorded_pixel_size(avatar_path) -> float | None:
    """The training frames' pixel width at the subject [m] that the fit at ``avatar_path`` (its output folder or
    its ``avatar.pt``) recorded in its ``training_poses.npz`` (:func:`warpavatar.fit.outputs.training_pixel_size`),
    or None where it has none (no such file, or a fit that predates the record)."""
    from pathlib import Path

    from warpavatar.fit.outputs import PIXEL_SIZE_KEY, TRAINING_MOTION_NAME

    path = Path(avatar_path)
    path = (path if path.is_dir() else path.parent) / TRAINING_MOTION_NAME
    if not path.is_file():
        return None
    with np.load(path) as arrays:
        if PIXEL_SIZE_KEY not in arrays.files:
            return None
        value = float(np.asarray(arrays[PIXEL_SIZE_KEY]).reshape(-1)[0])
    if not (np.isfinite(value) and value > 0.0):
        raise ValueError(f"{path}: {PIXEL_SIZE_KEY} must be a positive number of metres, got {value}")
    return value


def recorded_training_motion(avatar_path, skeleton):
    """The training motion the fit at ``avatar_path`` (its output folder or its ``avatar.pt``) wrote beside its
    avatar, as an :class:`~warpavatar.io.exporters.ExportMotion` for ``skeleton``, or None where it wrote none."""
    from pathlib import Path

    from warpavatar.fit.outputs import TRAINING_MOTION_NAME
    from warpavatar.io.exporters import ExportMotion
    from warpavatar.io.motion import load_motion

    path = Path(avatar_path)
    path = (path if path.is_dir() else path.parent) / TRAINING_MOTION_NAME
    if not path.is_file():
        return None
    return ExportMotion.from_motion(load_motion(path, skeleton))


def fit_posed_silhouettes(avatar, vertices: np.ndarray, faces: np.ndarray, motion, *, pixel_size: float,
                          voxel_size: float, rounds: int | None = None, device=None) -> np.ndarray:
    """The canonical surface's vertices moved so that, skinned as the export skins them, its silhouettes match
    the Gaussians' in frames of the fit's training motion, at the fit's training pixel.

    The surface is fused from renders of the avatar at rest, but what a user sees is the avatar moving, at about
    the resolution it was fitted at, and there the Gaussians' silhouette differs from the rest pose's: pose
    correction and skinning move them, and a soft edge that covers half a coarse pixel covers less of a fine one.
    The surface is skinned (:func:`~warpavatar.mesh.skin.skin_mesh`, :func:`~warpavatar.mesh.skin.mesh_animation`
    over the whole motion, so the per-frame offsets beyond skinning come with it), the avatar is rendered in
    :data:`~warpavatar.mesh.views.POSED_FRAMES` of its frames from cameras all around it
    (:func:`~warpavatar.mesh.views.render_posed_views`), and :func:`~warpavatar.mesh.surface.fit_silhouettes`
    moves the vertices with each view seeing them through its frame's skinning.

    Args:
        avatar: the :class:`~warpavatar.model.Avatar`.
        vertices: [V,3] canonical surface [m]; faces: [F,3].
        motion: the training motion (:func:`recorded_training_motion`).
        pixel_size: the training pixel's width at the subject [m] (:func:`recorded_pixel_size`).
        voxel_size: the fused grid's voxel [m] (the largest move a round).
        rounds: rounds of the fit (default :data:`~warpavatar.mesh.surface.SILHOUETTE_ROUNDS`).
        device: where to render (default: the avatar's device).

    Returns:
        [V,3] float64 moved vertices.
    """
    from warpavatar.mesh import skin as skinning
    from warpavatar.mesh import surface
    from warpavatar.mesh.views import posed_frames, render_posed_views

    device = avatar.gaussians.means.device if device is None else torch.device(device)
    rounds = surface.SILHOUETTE_ROUNDS if rounds is None else int(rounds)
    if rounds < 1 or faces.shape[0] == 0:
        return np.asarray(vertices, np.float64)
    bare = AvatarMesh(vertices=np.asarray(vertices, np.float32), faces=np.asarray(faces, np.int32),
                      normals=_vertex_normals(np.asarray(vertices, np.float32), np.asarray(faces)),
                      up=np.asarray(avatar.skeleton.up, dtype=np.float32))
    skinned = skinning.skin_mesh(avatar, bare, weights_from="gaussians")
    animation = skinning.mesh_animation(avatar, skinned, motion)
    frames = posed_frames(animation.frame_count)
    views, view_frames = render_posed_views(avatar, motion, frames, pixel_size=pixel_size, device=device)
    with torch.no_grad():
        dense = skinning._dense_weights(skinned, animation.joint_transforms.shape[1], device)
        poses = []
        for t in frames:
            transforms = torch.as_tensor(animation.joint_transforms[t], dtype=torch.float32, device=device)
            pose = torch.einsum("vj,jab->vab", dense, transforms)[:, :3, :].clone()  # [V,3,4]
            if animation.vertex_offsets is not None:  # offsets are added before skinning: A (x + o) + b
                offset = torch.as_tensor(animation.vertex_offsets[t], dtype=torch.float32, device=device)
                pose[..., 3] += torch.einsum("vij,vj->vi", pose[..., :3], offset)
            poses.append(pose)
    return surface.fit_silhouettes(np.asarray(vertices, np.float64), np.asarray(faces), views,
                                   voxel_size=voxel_size, rounds=rounds, poses=torch.stack(poses),
                                   view_poses=torch.as_tensor(view_frames), device=device)


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[V,3] float32 unit normals: the area-weighted sum of the normals of the faces around each vertex."""
    corners = vertices[faces].astype(np.float64)
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # |n| = 2 * area
    normals = np.zeros((vertices.shape[0], 3))
    for corner in range(3):
        np.add.at(normals, faces[:, corner], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    fallback = np.array([0.0, 0.0, 1.0])
    normals = np.where(length > 0, normals / np.maximum(length, 1e-30), fallback)
    return normals.astype(np.float32)


def build_avatar_mesh(avatar, *, triangles: int = DEFAULT_TRIANGLES, texture_size: int = DEFAULT_TEXTURE_SIZE,
                      view_count: int = DEFAULT_VIEW_COUNT, view_size: int = DEFAULT_VIEW_SIZE,
                      training_pixel_size: float | None = None, training_motion=None,
                      max_voxels: int | None = None, silhouette_rounds: int | None = None, device=None,
                      texture: bool = True, vertex_colors: bool = True, skin: bool = True, progress: bool = False,
                      timings: dict[str, float] | None = None, settings: dict | None = None) -> AvatarMesh:
    """The avatar's surface in its canonical pose, as a mesh an engine can texture and skin.

    Args:
        avatar: a fitted :class:`~warpavatar.model.Avatar`.
        triangles: triangles of the decimated surface (the result has about as many).
        texture_size: width and height of the texture atlas [px].
        view_count: renders of the canonical avatar the surface and colours come from.
        view_size: width and height of each render [px].
        training_pixel_size: the width [m] a pixel of the fit's training frames covers at the subject
            (:func:`recorded_pixel_size`): the renders then blur the Gaussians as the fit's renders did
            (:func:`~warpavatar.mesh.views.training_blur`), so the surface has the silhouette the fit matched to its
            masks; None: no blur (the Gaussians' own silhouette, thinner than the fit's at its resolution).
        training_motion: the fit's training motion (:func:`recorded_training_motion`): with
            ``training_pixel_size``, the surface is fitted to the Gaussians' silhouettes in its frames
            (:func:`fit_posed_silhouettes`); None: the fused surface as it is.
        max_voxels: most voxels of the fused grid (:func:`~warpavatar.mesh.surface.extract_surface`); None:
            :data:`~warpavatar.mesh.surface.MAX_VOXELS`.
        silhouette_rounds: rounds of :func:`fit_posed_silhouettes`; None:
            :data:`~warpavatar.mesh.surface.SILHOUETTE_ROUNDS`, 0: none.
        device: where to render (default: the avatar's device).
        texture: unwrap UVs and bake the texture atlas (``uvs``, ``texture``); off: the surface's vertices
            unsplit, ``uvs`` and ``texture`` None.
        vertex_colors: bake ``vertex_colors``.
        skin: add skin weights and the rig (``joint_*``).
        progress: show a progress bar over the stages, named as they run.
        timings: a dict to fill with each stage's wall time [s], by stage name, or None.
        settings: a dict to fill with what was chosen (``view_size`` [px], ``voxel_size`` [m], ``max_voxels``,
            ``silhouette_rounds``), or None.

    Returns:
        the :class:`AvatarMesh`, with the avatar skeleton's ``up``.

    Raises:
        ValueError: the avatar has no surface to extract (no Gaussians, or none opaque enough).
    """
    import tqdm

    from warpavatar.mesh import skin as skinning
    from warpavatar.mesh import surface, texture as texturing
    from warpavatar.mesh.views import render_canonical_views

    rounds = surface.SILHOUETTE_ROUNDS if silhouette_rounds is None else int(silhouette_rounds)
    posed_fit = training_motion is not None and training_pixel_size is not None and rounds > 0
    stages = ["views", "surface"] + (["silhouettes"] if posed_fit else []) + (["uvs", "texture"] if texture else []) \
        + (["vertex colours"] if vertex_colors else []) + (["skin"] if skin else [])
    timings = {} if timings is None else timings
    bar = tqdm.tqdm(total=len(stages), desc="mesh", unit="stage", disable=not progress)
    clock = [time.perf_counter()]

    def begin(stage: str) -> None:
        bar.set_postfix_str(stage, refresh=True)

    def end(stage: str) -> None:
        now = time.perf_counter()
        timings[stage] = now - clock[0]
        clock[0] = now
        bar.update(1)

    device = avatar.gaussians.means.device if device is None else torch.device(device)
    try:
        begin("views")
        views = render_canonical_views(avatar, count=view_count, size=view_size,
                                       training_pixel_size=training_pixel_size, device=device)
        end("views")

        begin("surface")
        max_voxels = surface.MAX_VOXELS if max_voxels is None else int(max_voxels)
        fused = surface.extract_surface(views, triangles=triangles, skeleton=avatar.skeleton, device=device,
                                        max_voxels=max_voxels)
        if settings is not None:
            settings.update(view_size=int(views[0].width), voxel_size=float(fused.metadata["voxel_size"]),
                            max_voxels=max_voxels, silhouette_rounds=rounds if posed_fit else 0)
        surface_vertices = np.asarray(fused.vertices, dtype=np.float32)
        surface_faces = np.asarray(fused.faces, dtype=np.int32)
        if surface_faces.shape[0] == 0:
            raise ValueError("the avatar's renders hold no surface to make a mesh of")
        surface_normals = _vertex_normals(surface_vertices, surface_faces)
        end("surface")

        if posed_fit:
            begin("silhouettes")
            surface_vertices = fit_posed_silhouettes(
                avatar, surface_vertices, surface_faces, training_motion, pixel_size=float(training_pixel_size),
                voxel_size=float(fused.metadata["voxel_size"]), rounds=rounds, device=device).astype(np.float32)
            surface_normals = _vertex_normals(surface_vertices, surface_faces)
            end("silhouettes")

        if texture:
            begin("uvs")
            vertices, faces, uvs, source_vertex = texturing.unwrap(surface_vertices, surface_faces,
                                                                   size=int(texture_size))
            vertices = np.asarray(vertices, dtype=np.float32)
            faces = np.asarray(faces, dtype=np.int32)
            source_vertex = np.asarray(source_vertex, dtype=np.int64)
            normals = surface_normals[source_vertex]  # split vertices along a seam keep one normal
            end("uvs")
            begin("texture")
            atlas = texturing.bake_texture(vertices, faces, normals, uvs, views, size=int(texture_size),
                                           device=device)
            end("texture")
        else:
            vertices, faces, normals, uvs, atlas = surface_vertices, surface_faces, surface_normals, None, None
            source_vertex = None

        colours = None
        if vertex_colors:  # on the unsplit surface, so a seam's split vertices get one colour
            begin("vertex colours")
            colours = texturing.vertex_colors(surface_vertices, surface_normals, views, device=device)
            colours = np.asarray(colours, dtype=np.uint8)
            if source_vertex is not None:
                colours = colours[source_vertex]
            end("vertex colours")

        mesh = AvatarMesh(vertices=vertices, faces=faces, normals=normals,
                          uvs=None if uvs is None else np.asarray(uvs, dtype=np.float32), texture=atlas,
                          vertex_colors=colours, up=np.asarray(avatar.skeleton.up, dtype=np.float32))
        if skin:
            begin("skin")
            mesh = skinning.skin_mesh(avatar, mesh, weights_from="gaussians")
            end("skin")
        return mesh
    finally:
        bar.close()
