"""The main job on an embedded default, with LeRobot's own commands:

1. record a small scripted ALOHA transfer-cube dataset (`lerobot-vib-record-sim`, 120x160, no Hub),
2. train VIB on it (`lerobot-train --policy.type=vib`),
3. calibrate its uncertainty on the training episodes (`lerobot-vib-calibrate`: R_bar, so u = R / R_bar),
4. roll the checkpoint out in the fast gym-aloha env with LeRobot's eval loop, the stop off, recording u per
   episode (`lerobot-vib-eval --env.type=aloha_fast --env.dataset_root=...`),
5. set the stop threshold gamma on those clean rollouts (`lerobot-vib-calibrate --rollouts=... --conformal_alpha`):
   the paper's mean + 2 std of training frames lies below the peak of u at every episode's start and would
   stop every rollout at step 1 (benchmarks/results: 100% false stops), the conformal threshold on rollouts
   bounds the false-stop rate by alpha,
6. trace u step by step in a rollout with an occlusion and the safety stop on
   (`examples/rollout_uncertainty.py`: trace.csv, summary.json, trace.png).

Each command is printed before it runs; outputs go to outputs/demo/. A CPU run of the defaults takes minutes
and is far too short to solve the task: it shows the pipeline, not a result. For a real run use 50 episodes,
480x640 and tens of thousands of steps on a GPU (see README).

    python examples/demo.py [--episodes 4] [--steps 200] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

BIN = Path(sys.executable).parent
REPO_ID = "local/demo_aloha_transfer_cube"
ROLLOUTS, ALPHA = 10, 0.1  # a conformal threshold at alpha = 0.1 needs at least 9 clean rollouts


def run(cmd: list[str]) -> None:
    print("\n$ " + " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--batch_size", type=int, default=8)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"))
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("SVT_LOG", "1")  # the AV1 encoder's info lines
    size = ["--image_height=120", "--image_width=160"]

    data = args.out / "data"
    record = [
        str(BIN / "lerobot-vib-record-sim"),
        "--task=transfer_cube",
        f"--num_episodes={args.episodes}",
        *size,
        "--shadows=false",
        f"--repo_id={REPO_ID}",
        f"--root={data}",
    ]
    if (data / "meta" / "info.json").exists():
        record.append("--resume=true")  # keeps what an earlier demo recorded
    run(record)

    train_dir = args.out / "train"
    shutil.rmtree(train_dir, ignore_errors=True)
    run(
        [
            str(BIN / "lerobot-train"),
            "--policy.type=vib",
            f"--dataset.repo_id={REPO_ID}",
            f"--dataset.root={data}",
            f"--policy.device={args.device}",
            "--policy.pretrained_backbone_weights=null",
            "--policy.push_to_hub=false",
            "--wandb.enable=false",
            f"--steps={args.steps}",
            f"--batch_size={args.batch_size}",
            f"--save_freq={args.steps}",
            "--log_freq=25",
            "--num_workers=2",
            f"--output_dir={train_dir}",
        ]
    )

    trained = train_dir / "checkpoints" / "last" / "pretrained_model"
    ckpt = trained.with_name("pretrained_model_calibrated")  # lerobot-vib-calibrate's default output
    run(
        [
            str(BIN / "lerobot-vib-calibrate"),
            f"--policy.path={trained}",
            f"--dataset.repo_id={REPO_ID}",
            f"--dataset.root={data}",
        ]
    )

    eval_dir = args.out / "eval"
    shutil.rmtree(eval_dir, ignore_errors=True)
    run(
        [
            str(BIN / "lerobot-vib-eval"),  # lerobot-eval, and u and the stops of every episode
            f"--policy.path={ckpt}",
            f"--policy.device={args.device}",
            "--env.type=aloha_fast",
            f"--env.dataset_root={data}",  # task, image size, cameras and shadows as recorded
            f"--eval.n_episodes={ROLLOUTS}",
            f"--eval.batch_size={ROLLOUTS}",
            f"--output_dir={eval_dir}",
        ]
    )
    run(
        [
            str(BIN / "lerobot-vib-calibrate"),
            f"--policy.path={ckpt}",
            f"--rollouts={eval_dir / 'uncertainty_info.json'}",
            f"--conformal_alpha={ALPHA}",
            "--threshold=max",  # one threshold for all steps: the time-indexed band needs twice the rollouts
            "--in_place=true",  # the calibrated copy this demo wrote above
        ]
    )

    trace_dir = args.out / "uncertainty"
    run(
        [
            sys.executable,
            str(Path(__file__).with_name("rollout_uncertainty.py")),
            f"--policy_path={ckpt}",
            "--occlude=150:230",
            "--safety",
            f"--device={args.device}",
            f"--out={trace_dir}",
        ]
    )

    overall = json.loads((eval_dir / "eval_info.json").read_text())["overall"]
    u_eval = json.loads((eval_dir / "uncertainty_info.json").read_text())["overall"]
    trace = json.loads((trace_dir / "summary.json").read_text())
    print(
        f"\nDataset: {data}\nCheckpoint (calibrated): {ckpt}\n"
        f"Eval: success {overall['pc_success']:.0f}% over {overall['n_episodes']} episodes, mean u "
        f"{u_eval['u_mean']:.2f}, mean max u {u_eval['u_max_mean']:.2f} ({eval_dir}/uncertainty_info.json), "
        f"video {overall['video_paths'][0]}\n"
        f"Uncertainty trace: {trace_dir}/trace.png; mean u on clean steps {trace['mean_u_clean']:.2f}, on "
        f"occluded steps {trace['mean_u_occluded']:.2f}, gamma {trace['gamma']:.2f}, "
        f"safety stops at steps {trace['stop_intervals'] or 'none'}\n"
        f"gamma is the conformal threshold on the {ROLLOUTS} clean rollouts above (at most {ALPHA:.0%} of clean "
        "rollouts stop); whether the occlusion crosses it depends on the policy, and one trained for minutes "
        "is far from its data everywhere, so read the trace, not the verdict. See README, 'Uncertainty at run time'."
    )


if __name__ == "__main__":
    main()
