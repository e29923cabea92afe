"""Camera calibrations for multi-view preparation: a pinhole camera with OpenCV lens distortion, and readers.

Two file formats are read:

* Qualisys ``.qca.txt`` (XML, as Pose2Sim ships its demo calibration). Intrinsics are stored in sensor units of
  1/64 pixel; the ``transform`` element holds the camera position in millimetres and a rotation ``r11..r33``
  whose rows, read naturally, map world directions to the Qualisys camera frame (x right, y up, z backward).
  OpenCV's camera frame (x right, y down, z forward) is that frame turned 180 degrees about x, so
  ``world_to_camera = diag(1, -1, -1) @ R_qualisys`` and ``t = -world_to_camera @ position``.
* OpenCV-style TOML (Pose2Sim, anipose): one table per camera with ``size = [width, height]``, ``matrix`` (K),
  ``distortions`` (k1, k2, p1, p2), ``rotation`` (Rodrigues vector, world to camera), ``translation`` (metres)
  and ``fisheye``.

All cameras follow the project's convention (docs/conventions.md, docs/FORMAT.md): x right, y down, z forward, the
centre of pixel (i, j) at image coordinates (i, j), world units in metres.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "CameraCalibration",
    "read_calibration",
    "read_qca",
    "read_toml",
    "rodrigues_to_matrix",
    "match_cameras",
]

# Qualisys stores intrinsics in sub-pixel sensor units: 64 units per pixel.
_QUALISYS_UNITS_PER_PIXEL = 64.0
# Turning the Qualisys camera frame (y up, z backward) into OpenCV's (y down, z forward).
_QUALISYS_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


@dataclasses.dataclass(frozen=True)
class CameraCalibration:
    """One calibrated camera.

    Attributes:
        name: camera name as the calibration file gives it (e.g. ``"cam01"``).
        width: image width [px] the intrinsics refer to.
        height: image height [px].
        K: intrinsics, shape [3, 3], float64, pixels (pixel centres at integer coordinates).
        distortion: OpenCV distortion coefficients (k1, k2, p1, p2, k3), shape [5], float64; for a fisheye
            camera the four coefficients (k1, k2, k3, k4) of OpenCV's fisheye model followed by a zero.
        world_to_camera: rigid transform from world to camera coordinates, shape [4, 4], float64, metres.
        fisheye: whether ``distortion`` follows OpenCV's fisheye model instead of the Brown-Conrady model.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    distortion: np.ndarray
    world_to_camera: np.ndarray
    fisheye: bool = False

    def __post_init__(self):
        K = np.asarray(self.K, dtype=np.float64)
        distortion = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
        world_to_camera = np.asarray(self.world_to_camera, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"camera {self.name!r}: K must have shape [3, 3], got {K.shape}")
        if world_to_camera.shape != (4, 4):
            raise ValueError(
                f"camera {self.name!r}: world_to_camera must have shape [4, 4], got {world_to_camera.shape}"
            )
        if distortion.size > 5:
            raise ValueError(
                f"camera {self.name!r}: at most 5 distortion coefficients are supported, got {distortion.size}"
            )
        if not (np.isfinite(K).all() and np.isfinite(distortion).all() and np.isfinite(world_to_camera).all()):
            raise ValueError(f"camera {self.name!r}: calibration contains non-finite values")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name!r}: image size must be positive, got {self.width}x{self.height}")
        rotation = world_to_camera[:3, :3]
        if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4) or np.linalg.det(rotation) < 0:
            raise ValueError(f"camera {self.name!r}: world_to_camera rotation is not a proper rotation")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "distortion", np.pad(distortion, (0, 5 - distortion.size)))
        object.__setattr__(self, "world_to_camera", world_to_camera)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def rotation(self) -> np.ndarray:
        """World-to-camera rotation, shape [3, 3]."""
        return self.world_to_camera[:3, :3]

    @property
    def translation(self) -> np.ndarray:
        """World-to-camera translation [m], shape [3]."""
        return self.world_to_camera[:3, 3]

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates [m], shape [3]."""
        return -self.rotation.T @ self.translation

    @property
    def has_distortion(self) -> bool:
        """Whether any distortion coefficient is non-zero."""
        return bool(np.any(self.distortion != 0.0))

    def projection_matrix(self) -> np.ndarray:
        """``K @ [R | t]``, shape [3, 4]: world points to homogeneous undistorted pixels."""
        return self.K @ self.world_to_camera[:3, :]

    def resized(self, width: int, height: int) -> "CameraCalibration":
        """The same camera for an image resampled to ``width`` x ``height`` pixels.

        With pixel centres at integer coordinates a pixel coordinate u maps to ``(u + 0.5) * s - 0.5`` under a
        scale s, so the focal lengths scale by s and the principal point by that affine map. Distortion acts on
        normalized coordinates and is unchanged.
        """
        scale_x = width / self.width
        scale_y = height / self.height
        K = self.K.copy()
        K[0, 0] *= scale_x
        K[0, 1] *= scale_x
        K[0, 2] = (K[0, 2] + 0.5) * scale_x - 0.5
        K[1, 1] *= scale_y
        K[1, 2] = (K[1, 2] + 0.5) * scale_y - 0.5
        return dataclasses.replace(self, width=int(width), height=int(height), K=K)

    def without_distortion(self) -> "CameraCalibration":
        """The ideal pinhole camera with the same K and pose (what undistorted images show)."""
        return dataclasses.replace(self, distortion=np.zeros(5), fisheye=False)

    def project(self, points: np.ndarray, *, distort: bool = True) -> np.ndarray:
        """Project world points to pixels.

        Args:
            points: world points [m], shape [..., 3].
            distort: apply the lens distortion (pixels of the raw image) or not (pixels of the undistorted one).

        Returns:
            Pixel coordinates, shape [..., 2], float64; points behind the camera give NaN.
        """
        points = np.asarray(points, dtype=np.float64)
        if points.shape[-1] != 3:
            raise ValueError(f"points must have shape [..., 3], got {points.shape}")
        camera_points = points @ self.rotation.T + self.translation
        depth = camera_points[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            normalized = camera_points[..., :2] / depth[..., None]
        normalized = np.where((depth > 0)[..., None], normalized, np.nan)
        if distort and self.has_distortion:
            normalized = self._distort_normalized(normalized)
        fx, fy, cx, cy, skew = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], self.K[0, 1]
        u = fx * normalized[..., 0] + skew * normalized[..., 1] + cx
        v = fy * normalized[..., 1] + cy
        return np.stack([u, v], axis=-1)

    def _distort_normalized(self, normalized: np.ndarray) -> np.ndarray:
        x, y = normalized[..., 0], normalized[..., 1]
        if self.fisheye:
            k1, k2, k3, k4 = self.distortion[:4]
            radius = np.sqrt(x * x + y * y)
            theta = np.arctan(radius)
            theta2 = theta * theta
            theta_d = theta * (1 + theta2 * (k1 + theta2 * (k2 + theta2 * (k3 + theta2 * k4))))
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(radius > 1e-12, theta_d / radius, 1.0)
            return np.stack([x * ratio, y * ratio], axis=-1)
        k1, k2, p1, p2, k3 = self.distortion
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x_distorted = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        y_distorted = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([x_distorted, y_distorted], axis=-1)

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """Map raw (distorted) pixel coordinates to the undistorted image with the same K.

        Args:
            pixels: raw image coordinates [px], shape [..., 2]; NaN entries stay NaN.

        Returns:
            Undistorted pixel coordinates, shape [..., 2], float64.
        """
        pixels = np.asarray(pixels, dtype=np.float64)
        if pixels.shape[-1] != 2:
            raise ValueError(f"pixels must have shape [..., 2], got {pixels.shape}")
        if not self.has_distortion or pixels.size == 0:
            return pixels.copy()
        K_inverse = np.linalg.inv(self.K)
        homogeneous = np.concatenate([pixels, np.ones(pixels.shape[:-1] + (1,))], axis=-1)
        distorted = (homogeneous @ K_inverse.T)[..., :2]
        normalized = self._undistort_normalized(distorted)
        ideal = np.concatenate([normalized, np.ones(normalized.shape[:-1] + (1,))], axis=-1) @ self.K.T
        result = ideal[..., :2]
        return result.reshape(pixels.shape)

    def _undistort_normalized(self, distorted: np.ndarray, iterations: int = 30) -> np.ndarray:
        """Invert :meth:`_distort_normalized` (fixed-point iterations, as OpenCV does; Newton for fisheye)."""
        if self.fisheye:
            k1, k2, k3, k4 = self.distortion[:4]
            theta_distorted = np.linalg.norm(distorted, axis=-1)
            theta = theta_distorted.copy()
            for _ in range(iterations):
                theta2 = theta * theta
                value = theta * (1 + theta2 * (k1 + theta2 * (k2 + theta2 * (k3 + theta2 * k4)))) - theta_distorted
                slope = 1 + theta2 * (3 * k1 + theta2 * (5 * k2 + theta2 * (7 * k3 + theta2 * 9 * k4)))
                theta = theta - value / slope
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(theta_distorted > 1e-12, np.tan(theta) / theta_distorted, 1.0)
            return distorted * ratio[..., None]
        k1, k2, p1, p2, k3 = self.distortion
        x, y = distorted[..., 0].copy(), distorted[..., 1].copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            delta_x = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            delta_y = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x = (distorted[..., 0] - delta_x) / radial
            y = (distorted[..., 1] - delta_y) / radial
        return np.stack([x, y], axis=-1)

    def undistortion_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Remap tables (for ``cv2.remap``) that turn a raw image of this camera's size into the undistorted one.

        Returns:
            Two float32 arrays of shape [height, width]: source x and y of every output pixel.
        """
        size = (self.width, self.height)
        if self.fisheye:
            return cv2.fisheye.initUndistortRectifyMap(
                self.K, self.distortion[:4], np.eye(3), self.K, size, cv2.CV_32FC1
            )
        return cv2.initUndistortRectifyMap(self.K, self.distortion, np.eye(3), self.K, size, cv2.CV_32FC1)

    def to_cameras_json(self) -> dict:
        """The ``cameras.json`` dictionary of docs/FORMAT.md (pinhole: the distortion is not represented)."""
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "world_to_camera": self.world_to_camera.tolist(),
            "frames": None,
        }


def rodrigues_to_matrix(rotation_vector) -> np.ndarray:
    """Rotation matrix of an axis-angle (Rodrigues) vector [rad], shape [3] -> [3, 3] float64."""
    vector = np.asarray(rotation_vector, dtype=np.float64).reshape(3)
    angle = float(np.linalg.norm(vector))
    if angle < 1e-12:
        return np.eye(3)
    axis = vector / angle
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * (cross @ cross)


def _float_attribute(element, name: str, path: Path) -> float:
    value = element.get(name)
    if value is None:
        raise ValueError(f"{path}: <{element.tag}> has no attribute {name!r}")
    try:
        return float(value)
    except ValueError:
        raise ValueError(f"{path}: <{element.tag}> attribute {name}={value!r} is not a number") from None


def read_qca(path) -> list[CameraCalibration]:
    """Read a Qualisys calibration (``.qca.txt``, XML).

    The image size is the ``fov_video`` window; intrinsics are divided by 64 (sensor sub-pixel units) and
    shifted by the window's top-left corner; a ``video_resolution`` attribute such as ``"720p"`` scales them
    from the 1080-line sensor mode. Distortion (radial k1..k3, tangential p1, p2) is used as OpenCV's model.

    Args:
        path: the ``.qca.txt`` file.

    Returns:
        One :class:`CameraCalibration` per ``<camera>`` element, in file order.

    Raises:
        ValueError: the file is not a Qualisys calibration or misses a field.
    """
    path = Path(path)
    try:
        root = ElementTree.parse(path).getroot()
    except ElementTree.ParseError as error:
        raise ValueError(f"{path}: not a valid Qualisys .qca XML file ({error})") from None
    camera_elements = root.findall("cameras/camera")
    if not camera_elements:
        raise ValueError(f"{path}: no <cameras>/<camera> element: not a Qualisys calibration")
    cameras = []
    for index, element in enumerate(camera_elements):
        name = element.get("serial") or f"camera{index:02d}"
        if float(element.get("viewrotation", "0") or 0) != 0:
            raise ValueError(f"{path}: camera {name!r} has a non-zero viewrotation, which is not supported")
        fov = element.find("fov_video")
        transform = element.find("transform")
        intrinsic = element.find("intrinsic")
        if fov is None or transform is None or intrinsic is None:
            raise ValueError(f"{path}: camera {name!r} lacks <fov_video>, <transform> or <intrinsic>")
        resolution_scale = 1.0
        video_resolution = element.get("video_resolution")
        if video_resolution and re.fullmatch(r"\d+p", video_resolution.strip()):
            resolution_scale = int(video_resolution.strip()[:-1]) / 1080.0
        left = _float_attribute(fov, "left", path)
        top = _float_attribute(fov, "top", path)
        width = (_float_attribute(fov, "right", path) - left + 1.0) * resolution_scale
        height = (_float_attribute(fov, "bottom", path) - top + 1.0) * resolution_scale

        def pixels(attribute: str) -> float:
            return _float_attribute(intrinsic, attribute, path) / _QUALISYS_UNITS_PER_PIXEL

        fx = pixels("focalLengthU") * resolution_scale
        fy = pixels("focalLengthV") * resolution_scale
        cx = (pixels("centerPointU") - left) * resolution_scale
        cy = (pixels("centerPointV") - top) * resolution_scale
        skew = float(intrinsic.get("skew", "0") or 0.0)
        K = np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        distortion = np.array([
            _float_attribute(intrinsic, "radialDistortion1", path),
            _float_attribute(intrinsic, "radialDistortion2", path),
            _float_attribute(intrinsic, "tangentalDistortion1", path),
            _float_attribute(intrinsic, "tangentalDistortion2", path),
            float(intrinsic.get("radialDistortion3", "0") or 0.0),
        ])
        rotation_qualisys = np.array(
            [[_float_attribute(transform, f"r{row}{column}", path) for column in (1, 2, 3)] for row in (1, 2, 3)]
        )
        position = np.array([_float_attribute(transform, axis, path) for axis in ("x", "y", "z")]) / 1000.0
        rotation = _QUALISYS_TO_OPENCV @ rotation_qualisys
        world_to_camera = np.eye(4)
        world_to_camera[:3, :3] = rotation
        world_to_camera[:3, 3] = -rotation @ position
        cameras.append(CameraCalibration(
            name=name, width=int(round(width)), height=int(round(height)), K=K, distortion=distortion,
            world_to_camera=world_to_camera,
        ))
    return cameras


def read_toml(path) -> list[CameraCalibration]:
    """Read an OpenCV-style TOML calibration (Pose2Sim / anipose layout).

    Every table holding a ``matrix`` key is a camera; others (``[metadata]``) are ignored. Keys: ``name``
    (defaults to the table name), ``size`` ([width, height] px), ``matrix`` (K), ``distortions`` (k1, k2, p1, p2
    [, k3]; the fisheye model's k1..k4 when ``fisheye = true``), ``rotation`` (Rodrigues vector, world to
    camera, rad) and ``translation`` (world to camera, metres).

    Args:
        path: the ``.toml`` file.

    Returns:
        One :class:`CameraCalibration` per camera table, in file order.

    Raises:
        ValueError: a camera table misses a key or has a value of the wrong shape.
    """
    path = Path(path)
    try:
        document = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise ValueError(f"{path}: not a valid TOML file ({error})") from None
    cameras = []
    for table_name, table in document.items():
        if not isinstance(table, dict) or "matrix" not in table:
            continue
        missing = [key for key in ("size", "matrix", "rotation", "translation") if key not in table]
        if missing:
            raise ValueError(f"{path}: camera table [{table_name}] lacks {', '.join(missing)}")
        size = np.asarray(table["size"], dtype=np.float64).reshape(-1)
        rotation_vector = np.asarray(table["rotation"], dtype=np.float64).reshape(-1)
        translation = np.asarray(table["translation"], dtype=np.float64).reshape(-1)
        if size.shape != (2,) or rotation_vector.shape != (3,) or translation.shape != (3,):
            raise ValueError(
                f"{path}: camera table [{table_name}] needs size [w, h], rotation [3] and translation [3], got "
                f"{size.shape}, {rotation_vector.shape}, {translation.shape}"
            )
        world_to_camera = np.eye(4)
        world_to_camera[:3, :3] = rodrigues_to_matrix(rotation_vector)
        world_to_camera[:3, 3] = translation
        fisheye = bool(table.get("fisheye", False))
        distortion = np.asarray(table.get("distortions", [0.0, 0.0, 0.0, 0.0]), dtype=np.float64).reshape(-1)
        if fisheye and distortion.size != 4:
            raise ValueError(f"{path}: fisheye camera [{table_name}] needs 4 distortion coefficients")
        cameras.append(CameraCalibration(
            name=str(table.get("name", table_name)), width=int(round(size[0])), height=int(round(size[1])),
            K=np.asarray(table["matrix"], dtype=np.float64), distortion=distortion,
            world_to_camera=world_to_camera, fisheye=fisheye,
        ))
    if not cameras:
        raise ValueError(f"{path}: no camera table (a table with a 'matrix' key) found")
    return cameras


def read_calibration(path) -> list[CameraCalibration]:
    """Read a calibration file, choosing the reader by its name: ``*.toml`` or Qualisys ``*.qca``/``*.qca.txt``.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the format is not recognised or the file is malformed.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file not found: {path}")
    name = path.name.lower()
    if name.endswith(".toml"):
        return read_toml(path)
    if name.endswith(".qca.txt") or name.endswith(".qca") or name.endswith(".xml"):
        return read_qca(path)
    raise ValueError(f"{path}: unknown calibration format (expected .toml or Qualisys .qca.txt)")


def _normalized_name(name: str) -> str:
    # "cam_01", "Cam01", "cam1" all become "cam1".
    lowered = re.sub(r"[^0-9a-z]", "", name.lower())
    return re.sub(r"(?<!\d)0+(?=\d)", "", lowered)


def match_cameras(video_names: list[str], cameras: list[CameraCalibration]) -> list[CameraCalibration]:
    """Pick, for every video, the calibrated camera of the same name.

    Names match exactly, else after lower-casing, dropping separators and leading zeros (``cam01`` matches
    ``cam_01`` and ``Cam1``), else a camera name contained in the video name and not followed by a digit
    (``cam01`` in ``walk_cam01``, but ``cam1`` not in ``cam10``).

    Args:
        video_names: the videos' file stems.
        cameras: the calibration's cameras.

    Returns:
        The matching camera of each video, same order.

    Raises:
        ValueError: a video matches no camera, or two videos match the same camera.
    """
    chosen = []
    for video_name in video_names:
        candidates = [camera for camera in cameras if camera.name == video_name]
        if not candidates:
            candidates = [camera for camera in cameras if _normalized_name(camera.name) == _normalized_name(video_name)]
        if not candidates:
            candidates = [
                camera for camera in cameras
                if re.search(re.escape(_normalized_name(camera.name)) + r"(?!\d)", _normalized_name(video_name))
            ]
        if len(candidates) != 1:
            available = ", ".join(camera.name for camera in cameras)
            raise ValueError(
                f"video {video_name!r} matches {len(candidates)} calibrated cameras (available: {available}); "
                "name each video after its camera"
            )
        chosen.append(candidates[0])
    names = [camera.name for camera in chosen]
    if len(set(names)) != len(names):
        raise ValueError(f"several videos match the same calibrated camera: {names}")
    return chosen
