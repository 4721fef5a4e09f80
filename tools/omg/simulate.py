"""Run batches of reaching clips: targets, contact logic and IK, 300 frames at 60 fps.

Per hand (spec §3.2): the hand is in contact when within ``CONTACT_RADIUS`` of its
current target; after ``CONTACT_FRAMES`` contact frames (counted only while in
contact) the hand's next target spawns. After the last one the target returns to the
hand's rest position and orientation and stays there. Each hand runs its own target
sequence. A target the hand has not reached after ``TARGET_TIMEOUT`` frames is
given up and the next one spawns (an addition: an IK with a fixed pelvis cannot
reach every spawn point; given-up targets are counted in the statistics).
"""

from __future__ import annotations

import numpy as np

from .ik import HandIK, IKParams
from .rigs import Rig, forward_kinematics, rest_positions
from .targets import MAX_REPS, clip_target_arrays

FRAMES = 300
CONTACT_RADIUS = 0.1
CONTACT_FRAMES = 5
TARGET_TIMEOUT = 90


def simulate(rig: Rig, plans: list[dict], params: IKParams = IKParams(), frames: int = FRAMES):
    """Simulate the clips of ``plans`` on ``rig`` as one batch.

    Returns a dict of float64 arrays over (B, T, ...):
    ``pos`` (B,T,J,3), ``rot`` (B,T,J,3,3), ``target_pos`` (B,T,K,3),
    ``target_rot`` (B,T,K,3,3), ``contact`` (B,T,K) for the K = 4 key joints (hands,
    then feet, whose targets are their rest poses), ``q`` (B,T,D), plus per-clip
    statistics ``reached`` / ``given_up`` (B, 2) target counts and ``reach_frames``
    (list of frame counts to contact).
    """
    B, J, D = len(plans), rig.n_joints, rig.n_dofs
    rest = rest_positions(rig)
    key = rig.key_joints
    pelvis_h = rest[0, 1]
    tpos_seq, trot_seq, n_reps = clip_target_arrays(plans, pelvis_h, rest[key[:2]])
    ik = HandIK(rig, params)

    q = np.zeros((B, D))
    v = np.zeros((B, D))
    idx = np.zeros((B, 2), dtype=np.int64)
    count = np.zeros((B, 2), dtype=np.int64)
    age = np.zeros((B, 2), dtype=np.int64)
    reached = np.zeros((B, 2), dtype=np.int64)
    given_up = np.zeros((B, 2), dtype=np.int64)
    reach_frames: list[int] = []

    out_pos = np.empty((B, frames, J, 3))
    out_rot = np.empty((B, frames, J, 3, 3))
    out_q = np.empty((B, frames, D))
    out_tpos = np.empty((B, frames, 4, 3))
    out_trot = np.empty((B, frames, 4, 3, 3))
    out_contact = np.empty((B, frames, 4), dtype=np.uint8)
    # Feet: static targets at their rest pose.
    out_tpos[:, :, 2:] = rest[key[2:]]
    out_trot[:, :, 2:] = np.eye(3)

    bi = np.arange(B)[:, None]
    hi = np.arange(2)[None, :]
    first_contact = np.full((B, 2), -1, dtype=np.int64)
    for t in range(frames):
        t_pos = tpos_seq[bi, hi, idx]  # (B, 2, 3)
        t_rot = trot_seq[bi, hi, idx]
        q, v = ik.step(q, v, t_pos, t_rot)
        P, G = forward_kinematics(rig, q)
        d_hands = np.linalg.norm(P[:, key[:2]] - t_pos, axis=-1)
        d_feet = np.linalg.norm(P[:, key[2:]] - rest[key[2:]], axis=-1)
        contact = np.concatenate([d_hands < CONTACT_RADIUS, d_feet < CONTACT_RADIUS], axis=1)

        out_pos[:, t] = P
        out_rot[:, t] = G
        out_q[:, t] = q
        out_tpos[:, t, :2] = t_pos
        out_trot[:, t, :2] = t_rot
        out_contact[:, t] = contact

        hc = contact[:, :2]
        active = idx < n_reps[:, None]  # still working through the spawned targets
        newly = hc & (first_contact < 0) & active
        first_contact[newly] = age[newly]
        count += hc
        age += 1
        done = active & (count >= CONTACT_FRAMES)
        timeout = active & ~done & (age >= TARGET_TIMEOUT)
        for b, h in zip(*np.nonzero(done)):
            reach_frames.append(int(first_contact[b, h]) + 1)
        reached += done
        given_up += timeout
        adv = done | timeout
        idx += adv
        count[adv] = 0
        age[adv] = 0
        first_contact[adv] = -1

    # Targets still pending at the end of the clip (neither reached nor given up).
    pending = np.clip(n_reps[:, None] - idx, 0, MAX_REPS)
    return dict(
        pos=out_pos,
        rot=out_rot,
        q=out_q,
        target_pos=out_tpos,
        target_rot=out_trot,
        contact=out_contact,
        reached=reached,
        given_up=given_up,
        pending=pending,
        reach_frames=reach_frames,
        rest_pos=rest,
    )
