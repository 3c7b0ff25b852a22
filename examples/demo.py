"""The main job on an embedded default: the simulated 6-DoF arm, with LeRobot's own commands.

1. record scripted grasps of a block in the arm's `near` workspace (`lerobot-vib-record-sim`, 48x64, no Hub),
2. train VIB's token network on them (`lerobot-train --config_path=configs/policy/vib_arm_sim.json
   --policy.encoder=tokens ...`, 3000 steps): the bottleneck on ACT's token memory, one token per cell of the
   trunk's 6x8 feature map. At 48x64 a training step costs about a third of one at the preset's 96x128, and
   this recipe was chosen over the pooled preset at the same training time on validation seeds, acting with
   ACT's temporal ensembling at m = 3.0 (benchmarks/results/demo_recipe_48x64_cpu_2core/README.md),
3. calibrate its uncertainty on the training episodes (`lerobot-vib-calibrate`: every score's training mean),
4. roll it out on 20 clean episodes with LeRobot's eval loop, the stop off, recording u per step
   (`lerobot-vib-eval --env.type=vib_arm`),
5. set the stop threshold on those rollouts (`lerobot-vib-calibrate --rollouts=... --conformal_alpha
   --threshold=std_band`): FAIL-Detect's time-indexed band on RND over the observation embedding, one
   threshold per episode step, such that at most 10% of clean rollouts should stop,
6. trace u step by step in one rollout with a board in front of the camera and the stop on
   (`examples/rollout_uncertainty.py`: trace.csv, summary.json, trace.png).

Each command is printed before it runs; everything goes to outputs/demo/. Interrupted, it resumes: a step whose
result is already there is skipped, and training continues from its last checkpoint. The full preset (7000
steps at 96x128, about 41 minutes on 2 cores) is in docs/arm.md; ALOHA's walk-through is in docs/aloha.md.

    python examples/demo.py [--episodes 50] [--steps 3000] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
PRESET = ROOT / "configs" / "policy" / "vib_arm_sim.json"
REPO_ID = "local/vib_arm_grasp_block_scripted"
ROLLOUTS, ALPHA = 20, 0.1  # the time-indexed band at alpha = 0.1 needs at least 18 clean rollouts
# The token network as the token preset starts it (narrow posteriors, z sampled when acting), on the preset's
# other fields; its floor stays on every feature, which the token network's floor choice kept at 2000 steps
# (benchmarks/results/floor_choice_tokens_demo_budget_cpu_2core/report.md).
TOKENS = ["--policy.encoder=tokens", "--policy.posterior_logvar_init=-6.0", "--policy.sample_latent_at_inference=true"]
IMAGE = ["--image_height=48", "--image_width=64"]  # the trunk's map is 6x8 cells
# ACT's temporal ensembling weighted towards each step's oldest prediction: at this recipe's 3000 steps m = 3.0
# solved 31/40 validation episodes against 26/40 at the preset's 0.3, and 71/100 test episodes against 44/100
# (benchmarks/results/demo_recipe_48x64_cpu_2core/README.md).
ENSEMBLE = "--policy.temporal_ensemble_coeff=3.0"
# The stop's score and threshold, chosen for this recipe (m = 3.0) on validation rollouts by the default score's
# rule: RND on the observation embedding with FAIL-Detect's band stopped 28/40 occlusions within 5 steps at 3/40
# clean stops (benchmarks/results/demo_recipe_48x64_cpu_2core/score_choice_m3.md).
SCORE, THRESHOLD = "embedding_rnd", "std_band"
OCCLUDE = "30:60"  # the board is in front of the camera from step 30 to 59, as in the paper's Fig. 3c


TIMES: dict[str, float] = {}  # minutes per stage, printed at the end


def run(cmd: list[str]) -> None:
    """Run one command, printed as a user would type it; its time counts towards the stage its tool names."""
    words = [str(c) for c in cmd]
    shown = [Path(w).name if w.startswith(str(BIN)) else w for w in words]
    shown = [w.replace(str(ROOT) + "/", "") for w in shown]
    print("\n$ " + " ".join(shown), flush=True)
    start = time.time()
    subprocess.run(words, check=True)
    stage = Path(shown[1]).stem if shown[0] == "python" or shown[0].startswith("python") else shown[0]
    TIMES[stage] = TIMES.get(stage, 0.0) + (time.time() - start) / 60


def trained_steps(train_dir: Path) -> int:
    """The step of the last checkpoint LeRobot saved there (0 if none)."""
    state = train_dir / "checkpoints" / "last" / "training_state" / "training_step.json"
    return json.loads(state.read_text())["step"] if state.is_file() else 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"))
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("SVT_LOG", "1")  # the AV1 encoder's info lines
    start = time.time()

    data = args.out / "data"
    record = [BIN / "lerobot-vib-record-sim", "--task=grasp_block", "--workspace=near", *IMAGE]
    record += [f"--num_episodes={args.episodes}", f"--root={data}"]
    if (data / "meta" / "scripted_recording.json").exists():
        record.append("--resume=true")  # keeps what an earlier run recorded, finishes what it did not
    run(record)

    train_dir = args.out / "train"
    done = trained_steps(train_dir)
    if done < args.steps:
        train = [BIN / "lerobot-train"]
        if done:  # LeRobot's resume: the saved train config, model and optimizer state
            config = train_dir / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
            train += [f"--config_path={config}", "--resume=true"]
        else:
            train += [f"--config_path={PRESET}", f"--dataset.root={data}", f"--output_dir={train_dir}"]
            train += [*TOKENS, ENSEMBLE, f"--policy.uncertainty_score={SCORE}", f"--policy.device={args.device}"]
            train += [f"--save_freq={max(args.steps // 3, 1)}"]
        train += [f"--steps={args.steps}", "--log_freq=100"]
        run(train)

    trained = train_dir / "checkpoints" / "last" / "pretrained_model"
    ckpt = trained.with_name("pretrained_model_calibrated")  # lerobot-vib-calibrate's default output
    if not (ckpt / "model.safetensors").is_file():
        run(
            [
                BIN / "lerobot-vib-calibrate",
                f"--policy.path={trained}",
                f"--dataset.repo_id={REPO_ID}",
                f"--dataset.root={data}",
            ]
        )

    eval_dir = args.out / "eval"
    if not (eval_dir / "uncertainty_info.json").is_file():
        run(
            [
                BIN / "lerobot-vib-eval",  # lerobot-eval, and u and the stops of every episode
                f"--policy.path={ckpt}",
                f"--policy.device={args.device}",
                "--env.type=vib_arm",
                f"--env.dataset_root={data}",  # workspace, image size and camera as recorded
                f"--eval.n_episodes={ROLLOUTS}",
                "--eval.batch_size=10",
                "--eval.use_async_envs=false",
                f"--output_dir={eval_dir}",
            ]
        )
    run(
        [
            BIN / "lerobot-vib-calibrate",
            f"--policy.path={ckpt}",
            f"--rollouts={eval_dir / 'uncertainty_info.json'}",
            f"--conformal_alpha={ALPHA}",
            f"--threshold={THRESHOLD}",
            "--in_place=true",  # the calibrated copy written above
        ]
    )

    trace_dir = args.out / "occluded"
    run(
        [
            sys.executable,
            Path(__file__).with_name("rollout_uncertainty.py"),
            "--task=grasp_block",
            "--workspace=near",
            "--seed=1000",  # a block pose the recording (seeds from 0) did not use
            f"--policy_path={ckpt}",
            f"--occlude={OCCLUDE}",
            "--safety",
            f"--device={args.device}",
            f"--out={trace_dir}",
        ]
    )

    overall = json.loads((eval_dir / "eval_info.json").read_text())["overall"]
    u_eval = json.loads((eval_dir / "uncertainty_info.json").read_text())["overall"]
    band = json.loads((ckpt / "config.json").read_text())["calibration"]["gamma_band"]
    trace = json.loads((trace_dir / "summary.json").read_text())
    stops = "; ".join(f"steps {s['first_step']}-{s['last_step']}, ended: {s['ended']}" for s in trace["stops"])
    stages = ", ".join(f"{name} {minutes:.1f}" for name, minutes in TIMES.items())
    print(
        f"\nDone in {(time.time() - start) / 60:.1f} min (this run's commands, in minutes: {stages}).\n"
        f"Dataset: {data} ({args.episodes} scripted grasps)\n"
        f"Checkpoint (calibrated, gamma set): {ckpt}\n"
        f"Clean rollouts: success {overall['pc_success']:.0f}% over {overall['n_episodes']} episodes; mean u "
        f"{u_eval['u_mean']:.2f}, mean of each episode's max u {u_eval['u_max_mean']:.2f}; stop threshold "
        f"{min(band):.2f}-{max(band):.2f} over the episode (at most {ALPHA:.0%} of clean rollouts stop). "
        f"Videos: {Path(overall['video_paths'][0]).parent}\n"
        f"Occluded rollout (board over steps {OCCLUDE}, stop on): mean u {trace['mean_u_clean']:.2f} on clean "
        f"steps, {trace['mean_u_occluded']:.2f} under the board; stops: {stops or 'none'}; "
        f"{'grasped' if trace.get('success') else 'not grasped'}. Picture: {trace_dir / 'trace.png'}\n"
        f"\nNext: the token preset at 96x128, 97% of clean test episodes over three training seeds (81 min for its "
        "7000 steps on 2 cores, docs/arm.md):\n"
        "  lerobot-vib-record-sim --task=grasp_block --workspace=near --num_episodes=50 --root=data/arm_near\n"
        "  lerobot-train --config_path=configs/policy/vib_arm_tokens.json --dataset.root=data/arm_near "
        "--output_dir=outputs/train/vib_arm_tokens"
    )


if __name__ == "__main__":
    main()
