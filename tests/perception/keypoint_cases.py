"""The keypoint tests' own target: a box with a fin on top, 8 keypoints (four corners below, two above, the fin's
two tips) that a half-turn about z maps onto one another (a <-> b, c <-> d, e <-> f, fin1 <-> fin2). In one grey
material nothing breaks that half-turn (its twins look the same); with the fin painted in two colours, one per
side of the turn's axis, the materials break it. Written by the tests, not a shipped file."""

KEYPOINTS_T_M = {"a": (0.6, 0.3, -0.2), "b": (-0.6, -0.3, -0.2), "c": (0.6, -0.3, -0.2), "d": (-0.6, 0.3, -0.2),
                 "e": (0.6, 0.3, 0.2), "f": (-0.6, -0.3, 0.2), "fin1": (0.4, 0.0, 0.5), "fin2": (-0.4, 0.0, 0.5)}
HALF_TURN_PERM = [1, 0, 3, 2, 5, 4, 7, 6]  # R_z(180 deg) takes keypoint k onto keypoint HALF_TURN_PERM[k]


def twin_box_xml(name: str = "twin_box", painted: bool = False) -> str:
    """The target file; painted: the fin's +x half red (the materials break the half-turn)."""
    fin = ('<geom name="fin" type="box" pos="0 0 0.35" size="0.4 0.02 0.15" material="grey"/>' if not painted else
           '<geom name="fin_fore" type="box" pos="0.2 0 0.35" size="0.2 0.02 0.15" rgba="0.9 0.1 0.1 1"/>'
           '<geom name="fin_aft" type="box" pos="-0.2 0 0.35" size="0.2 0.02 0.15" material="grey"/>')
    sites = "".join(f'<site name="kp_{k}" pos="{x} {y} {z}"/>' for k, (x, y, z) in KEYPOINTS_T_M.items())
    return (f'<mujoco model="{name}"><asset><material name="grey" rgba="0.7 0.7 0.7 1" specular="0.3"/></asset>'
            '<worldbody><body name="target"><inertial pos="0 0 0" mass="40" diaginertia="1.5 3.0 3.5"/>'
            f'<geom name="hull" type="box" size="0.6 0.3 0.2" material="grey"/>{fin}{sites}</body></worldbody>'
            '</mujoco>')


# a training config small enough for a test (a 64 px network, a few steps)
SMALL_TRAIN = ("warmup_steps = 2\ncheckpoint_every = 1000000\nbatch_size = 4\n[model]\ninput_px = 64\nwidth = 16\n"
               "depth = 2\nstem_width = 8\n[data]\ninput_px = 64\nwhole_frame_prob = 0.1\n")


def untrained_weights(path, target_file, sigma_px: float | None = None) -> str:
    """Untrained keypoint weights (a 64 px network, seed 0) recording the target of target_file, written at path;
    with sigma_px, the calibration's metadata (that sigma for every keypoint), else none. Returns the path."""
    import json

    from envisat_pose.perception.keypoint_net import KeypointModelConfig, init_keypoint_net
    from envisat_pose.perception.weights import save_weights
    from envisat_pose.perception.weights_keys import SIGMA_KEY
    from envisat_pose.target import load_target

    target = load_target(str(target_file))
    record = {k: v for k, v in target.record(str(target_file)).items() if k != "file"}
    net = init_keypoint_net(KeypointModelConfig(input_px=64, width=8, depth=2, stem_width=8,
                                                num_keypoints=target.num_keypoints), 0, record)
    save_weights(str(path), net, None if sigma_px is None else {SIGMA_KEY: json.dumps([sigma_px] * target.num_keypoints)})
    return str(path)
