"""warpavatar's input: video folders and subjects (``docs/FORMAT.md``, ``docs/data.md``).

A *video folder* holds the frames of one camera, their masks, the camera, the skeleton and the per-frame bone
transforms. A *subject* groups a training video folder with held-out ``novel_view/`` and ``novel_pose/``
folders that share its skeleton and world frame.

* :mod:`~warpavatar.data.types`: :class:`Skeleton`, :class:`Camera`, :class:`VideoFolder`, :class:`Subject`;
* :mod:`~warpavatar.data.reader`: :func:`load_video_folder`, :func:`load_subject`, the demo subject;
* :mod:`~warpavatar.data.writer`: :func:`write_video_folder` and :func:`staged_folder`, the one atomic writer,
  and :func:`write_poses` (a poses.npz on its own);
* :mod:`~warpavatar.data.importers`: :func:`import_instantavatar`;
* :mod:`~warpavatar.data.checks`: the validators, and :class:`VideoFolderError`.

Everything read is checked; a problem raises :class:`VideoFolderError` whose message starts with the path of
the offending file and says what is wrong with it.
"""

from warpavatar.data.checks import RIGID_TOLERANCE, VideoFolderError
from warpavatar.data.importers import import_instantavatar
from warpavatar.data.reader import LazyVideoFolders, demo_subject_path, load_subject, load_video_folder, read_poses
from warpavatar.data.types import (ESTIMATED_POSES, POSE_SOURCES, SKELETON_FORMAT, Camera, Skeleton, Subject,
                                   VideoFolder)
from warpavatar.data.writer import staged_folder, write_poses, write_video_folder

__all__ = ["SKELETON_FORMAT", "ESTIMATED_POSES", "POSE_SOURCES", "RIGID_TOLERANCE", "VideoFolderError", "Skeleton",
           "Camera", "VideoFolder", "Subject",
           "LazyVideoFolders", "load_video_folder", "load_subject", "write_video_folder", "write_poses", "read_poses",
           "staged_folder", "import_instantavatar", "demo_subject_path"]
