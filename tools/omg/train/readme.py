"""Write README.md of trained model directories from their config.json (no PyTorch).

    python3 -m tools.omg.train.readme models/omg/tiny_fe_r1 [more dirs]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def readme(d: Path) -> str:
    c = json.loads((d / "config.json").read_text())
    t = c["training"]
    s = c["sizes"]
    m = c["macs_per_frame"]
    files = sorted(p.name for p in d.iterdir() if p.is_file() and p.name != "README.md")
    if "train_s" in t:
        times = f"training {t['train_s']} s"
    else:
        times = f"AE pre-training {t['ae_pretrain_s']} s, OMG training {t['omg_train_s']} s"
    wall = (f"Seed {t['seed']}; {t['threads']} thread(s); torch {t['torch']}, Python {t['python']}. Wall time on the"
            f" shared 2-core machine: {times}, {t['total_wall_s']} s in all (with export). Training clips:"
            f" {t['train_clips']}.")
    sizes = {p: (d / p).stat().st_size for p in files}
    lines = [
        f"# {d.name}",
        "",
        f"{c['variant']}-OMG on rig {c['rig']} (J = {c['J']}, K = {c['K']}), trained for **{c['mode']}** inference.",
        "",
        "Reproduce (repository root, data from `python3 -m tools.omg.generate --out data/omg --seed 0 --rigs R1,R4`,"
        " PyTorch from `tools/omg/requirements-train.txt`):",
        "",
        "```sh",
        t["command"],
        "```",
        "",
        wall,
        "",
        f"Sizes: AE hidden {s['ae_hidden']}, latent L {s['latent']}, cost encoder {s['cost_hidden']}, experts"
        f" {s['experts']} x hidden {s['expert_hidden']}, gate hidden {s['gate_hidden']}"
        + (f", RBF clusters {s['clusters']}" if c["variant"] == "RBF-CAT" else "")
        + f". **{c['params']:,} parameters, {m['total']:,} MACs per frame** ("
        + ", ".join(f"{k} {v:,}" for k, v in m.items() if k != "total")
        + "; experts counted k times, softmax/ELU/blend and grounded cost recomputation not counted).",
        "",
    ]
    if t.get("shared_from"):
        lines += [
            f"Rig transfer: CostEnc, gate and experts copied from `{t['shared_from']}`"
            + (" and **frozen** (only the autoencoder trained, 'Frozen')." if t["frozen_shared"] else " (all trained)."),
            f"Normalisation of the phase, cost and target blocks is the source model's; the pose block's is this rig's.",
            "",
        ]
    dof = c.get("pose_form") == "dof_velocity"
    if dof:
        a = t["args"]
        lines += [
            f"**Joint-velocity model** (`docs/omg-joint-velocity.md`): the decoder outputs the desired velocity of the"
            f" rig's {s['dof']} DOFs; the controller limits it and rebuilds the pose by forward kinematics. Recipe"
            f" (`tools/omg/train/dagger.py`): {a['tf_steps']} teacher-forced steps, then {a['dagger']} DAgger"
            f" iterations of {a['dagger_steps']} steps (batches of {a['train_batch']} frames, the IK's desired velocity"
            f" as the label at every visited state, the last {a['keep']} rollouts kept, learning rate {a['lr']} to"
            f" {a['lr_end']}, joint-position loss weight {a['pos_loss']}). Final loss {t['final_loss']:.4f}.",
            "",
        ]
    else:
        lines += [
            f"Final losses (normalised MSE over the whole frame): train {t['final_train_loss']:.4f} (last epoch, mixed"
            f" teacher forcing/autoregression), validation one-step {t['final_val_one_step']:.4f}.",
            "",
        ]
    q = c.get("qat")
    if q and dof:
        dg = q["dagger"]
        lines += [
            f"**Then fine-tuned for its int{q['weight_bits']} blob**: the command above, run with `--out {q['source']}`,"
            " wrote the model that",
            "",
            "```sh",
            q["command"],
            "```",
            "",
            f"fine-tuned with {dg['iterations']} DAgger iterations of {dg['steps']} steps (learning rate {q['lr']} to"
            f" {dg['lr_end']}, {q['qat_s']} s) with every weight matrix rounded to the blob's grid in each step and in"
            " every rollout"
            + (" (only the autoencoder; the shared nodes on the grid of the motion blob of"
               f" `{q['motion_from']}`)" if q.get("motion_from") else "")
            + f", then stored the weights as the blob computes them (snapped {len(q['snaps'])} times until nothing"
            " moved). `history.json` and `train.log` are the source's training; `qat_history.json` and `qat.log`"
            " the fine-tuning's.",
            "",
        ]
    elif q:
        lines += [
            f"**Then fine-tuned for its int{q['weight_bits']} blob** (quantisation-aware training, docs/omg.md): the"
            f" command above, run with `--out {q['source']}`, wrote the model that",
            "",
            "```sh",
            q["command"],
            "```",
            "",
            f"trained it {q['epochs']} epochs more ({q['train_clips']} clips, learning rate {q['lr']}, {q['qat_s']} s)"
            " with every weight matrix rounded to the blob's grid in each step"
            + (" (only the autoencoder; the shared nodes on the grid of the motion blob of"
               f" `{q['motion_from']}`)" if q.get("motion_from") else "")
            + (f" and Gaussian noise of standard deviation {q['feedback_noise']} (normalised units) on every"
               " fed-back frame" if q.get("feedback_noise") else "")
            + f", then stored the weights as the blob computes them (snapped {len(q['snaps'])} times until"
            f" nothing moved). Validation one-step loss after: {q['final_val_one_step']:.4f}. `history.json` and"
            " `train.log` are the source's training; `qat_history.json` and `qat.log` the fine-tuning's.",
            "",
        ]
    lines += [
        "| file | bytes | content |",
        "|---|---|---|",
    ]
    desc = {
        "model.safetensors": f"layer weights ({c.get('weights_dtype', 'float32')}) and `norm.mean`/`norm.std`"
        + (" and `norm.dof_mean`/`norm.dof_std`" if c.get("pose_form") == "dof_velocity" else "")
        + " (float32); names and shapes in `tools/omg/omg_np.py`",
        "config.json": "sizes, slices, out slices, phase-update constant, mode, normalisation, params, MACs, training"
        " (and fine-tuning) record",
        "history.json": "per-stage losses (and, for joint-velocity models, the closed-loop reach on training clips)",
        "train.log": "training log",
        "qat_history.json": "per-stage losses of the quantisation-aware fine-tuning",
        "qat.log": "quantisation-aware fine-tuning log",
        "rig.json": "the generator's rig description (joints, parents, rest pose, DOFs and limits)",
        "references.npz": "reference arrays (compressed, float32), below",
        "choice.json": "the fine-tuning runs this model was chosen among (`tools.omg.train.choose`): each run's"
        " figures on the training clips, which chose, and on the held-out clips, measured after; the rule; the kept run",
    }
    for f in files:
        desc_f = desc.get(f, desc.get(f.rsplit(".", 1)[0], ""))
        lines.append(f"| `{f}` | {sizes[f]:,} | {desc_f} |")
    lines += [
        "",
        f"`references.npz` holds held-out test rows {c['reference']['test_rows']} and PyTorch's outputs for them,"
        " computed in float64 from the stored weights (`python3 -m tools.omg.train.references`);"
        " `tools/omg/tests/test_models.py` checks that the NumPy forward pass reproduces them:",
        "",
        "| array | content |",
        "|---|---|",
    ]
    lines += [f"| `{k}` | {v} |" for k, v in c["reference"]["arrays"].items()]
    lines += [""]
    return "\n".join(lines)


if __name__ == "__main__":
    for a in sys.argv[1:]:
        p = Path(a)
        (p / "README.md").write_text(readme(p))
        print(f"wrote {p / 'README.md'}")
