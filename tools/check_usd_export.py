"""Check that a USD animation written by warpavatar-animate reads back exactly what the avatar poses.

    python tools/check_usd_export.py AVATAR_DIR MOTION_VIDEO_FOLDER FILE.usdc [FILE.usdc ...]

For each file: the largest absolute difference, over every frame, between the positions, orientations and
scales read back with pxr and the avatar posed by the same motion, and between the authored-once opacities
and SH coefficients and the avatar's. Zeros mean an exact round trip.
"""

import sys, time, numpy as np, torch
from warpavatar.model import Avatar
from warpavatar.io.usd import read_gaussian_usd
from warpavatar import data
avatar = Avatar.load(sys.argv[1])
video = data.load_video_folder(sys.argv[2])
motion = video.bone_transforms
avatar.prepare_sequence(motion, frame_ids=video.frame_ids, fps=video.fps)  # as warpavatar-animate does
for path in sys.argv[3:]:
    t0 = time.time(); usd = read_gaussian_usd(path)
    worst_pos = worst_quat = worst_scale = 0.0
    with torch.no_grad():
        grid = avatar.field.grid_weights()
        for t in range(motion.shape[0]):
            posed = avatar.pose(torch.as_tensor(motion[t]), grid=grid)
            worst_pos = max(worst_pos, float(np.abs(usd["positions"][t] - posed["means"].numpy()).max()))
            worst_quat = max(worst_quat, float(np.abs(usd["orientations"][t] - posed["quats"].numpy()).max()))
            worst_scale = max(worst_scale, float(np.abs(usd["scales"][t] - posed["scales"].numpy()).max()))
    opac = float(np.abs(usd["opacities"] - avatar.gaussians.opacities.detach().numpy()).max())
    sh = float(np.abs(usd["sh_coeffs"] - avatar.gaussians.sh_coefficients().detach().numpy()).max())
    print(f"{path}: {usd['layout']}, {len(usd['time_codes'])} time codes, {usd['positions'].shape[1]} Gaussians; "
          f"max |diff| positions {worst_pos:.2e}, quats {worst_quat:.2e}, scales {worst_scale:.2e}, "
          f"opacities {opac:.2e}, SH {sh:.2e}; fps {usd['fps']}, up {usd['up_axis']}")
