"""Run batches of reaching clips: targets, contact logic and IK, 300 frames at 60 fps.

Per hand (spec §3.2): the hand is in contact when within ``CONTACT_RADIUS`` of its
current target; after ``CONTACT_FRAMES`` contact frames (counted only while in
contact) it is done. The two hands' targets come in pairs (spec §3.2's adjacent or
opposite spawn points) that are certified reachable together, and the next pair spawns
when both hands are done (an earlier version ran each hand's sequence on its own, and
then a pair that the shared spine cannot serve could be due at once). After the last
pair the targets return to the hands' rest positions and orientations and stay there.
A pair not done after ``TARGET_TIMEOUT`` frames is given up and the next one spawns (an
addition: every target is reachable, so this only bounds a slow reach; given-up targets
are counted in the statistics). A pair due when fewer than ``LAST_SPAWN`` frames of the
clip remain is not spawned: the hands go back to rest instead (``spawned`` counts the
targets each hand was given).
"""

from __future__ import annotations

import numpy as np

from .ik import HandIK, IKParams
from .rigs import Rig, forward_kinematics, rest_positions
from .targets import MAX_REPS, clip_target_arrays

FRAMES = 300
CONTACT_RADIUS = 0.1
CONTACT_FRAMES = 5
TARGET_TIMEOUT = 150
LAST_SPAWN = 100


def simulate(rig: Rig, plans: list[dict], params: IKParams = IKParams(), frames: int = FRAMES,
             targets=None):
    """Simulate the clips of ``plans`` on ``rig`` as one batch.

    The two hands' k-th targets spawn together as a pair (they are certified reachable
    together, :mod:`tools.omg.targets`). A hand that has been in contact for
    ``CONTACT_FRAMES`` frames is done and holds its target; the next pair spawns when
    both hands are done, or when the pair is ``TARGET_TIMEOUT`` frames old (the hands not
    done then gave their targets up). After the last pair both targets return to rest.

    Returns a dict of float64 arrays over (B, T, ...):
    ``pos`` (B,T,J,3), ``rot`` (B,T,J,3,3), ``target_pos`` (B,T,K,3),
    ``target_rot`` (B,T,K,3,3), ``contact`` (B,T,K) for the K = 4 key joints (hands,
    then feet, whose targets are their rest poses), ``q`` (B,T,D), plus per-clip
    statistics ``spawned`` / ``reached`` / ``given_up`` / ``pending`` (B, 2) target
    counts, ``moved`` (B, 2, MAX_REPS) (cylinder pairs pulled in to be reachable),
    ``reach_frames`` (list of frame counts to contact) and the targets themselves,
    ``targets`` (B, 2, MAX_REPS, 3). ``targets``: precomputed
    :func:`tools.omg.targets.clip_target_arrays` of ``plans`` on ``rig``, if at hand.
    """
    B, J, D = len(plans), rig.n_joints, rig.n_dofs
    rest = rest_positions(rig)
    key = rig.key_joints
    tpos_seq, trot_seq, n_reps, moved = targets if targets is not None else clip_target_arrays(rig, plans)
    ik = HandIK(rig, params)

    q = np.zeros((B, D))
    v = np.zeros((B, D))
    idx = np.zeros(B, dtype=np.int64)  # the current pair, per clip
    n_spawned = (n_reps > 0).astype(np.int64)  # pairs spawned so far
    count = np.zeros((B, 2), dtype=np.int64)
    done = np.zeros((B, 2), dtype=bool)
    age = np.zeros(B, dtype=np.int64)
    reached = np.zeros((B, 2), dtype=np.int64)
    given_up = np.zeros((B, 2), dtype=np.int64)
    first_contact = np.full((B, 2), -1, dtype=np.int64)
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

    bi = np.arange(B)
    for t in range(frames):
        t_pos = tpos_seq[bi, :, idx]  # (B, 2, 3)
        t_rot = trot_seq[bi, :, idx]
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
        active = (idx < n_reps)[:, None] & ~done  # hands still working on a spawned target
        newly = hc & (first_contact < 0) & active
        first_contact[newly] = age[:, None].repeat(2, 1)[newly]
        count += hc & active
        age += 1
        finish = active & (count >= CONTACT_FRAMES)
        for b, h in zip(*np.nonzero(finish)):
            reach_frames.append(int(first_contact[b, h]) + 1)
        reached += finish
        done |= finish
        timeout = (idx < n_reps) & ~done.all(axis=1) & (age >= TARGET_TIMEOUT)
        given_up += timeout[:, None] & ~done
        adv = (idx < n_reps) & (done.all(axis=1) | timeout)
        idx += adv
        # Too late in the clip for another reach: back to rest.
        late = adv & (idx < n_reps) & (frames - (t + 1) < LAST_SPAWN)
        idx[late] = n_reps[late]
        n_spawned += adv & (idx < n_reps)
        count[adv] = 0
        done[adv] = False
        age[adv] = 0
        first_contact[adv] = -1

    spawned = np.repeat(n_spawned[:, None], 2, axis=1)
    # Spawned targets still pending at the end of the clip (neither reached nor given up).
    pending = spawned - reached - given_up
    return dict(
        pos=out_pos,
        rot=out_rot,
        q=out_q,
        target_pos=out_tpos,
        target_rot=out_trot,
        contact=out_contact,
        spawned=spawned,
        reached=reached,
        given_up=given_up,
        pending=pending,
        moved=moved,
        targets=tpos_seq[:, :, :MAX_REPS],
        reach_frames=reach_frames,
        rest_pos=rest,
    )
