"""What ORs of three and a margin over the conformal thresholds change in the shipped failure monitor.

An OR of monitors (`lerobot_vib.failure.AnyOf`) alarms when any member does, each member calibrated at
alpha / k. With two members the report's rule could not find one that is both early and quiet on validation:
the scores that see a scene wrong from its first frame (a black or dimmed camera: the embedding RND, the low
image rate, the map's cold cells) also see colour jitter and noise that the policy handles, and an OR with
them stops those benign successes; without them the alarm waits for the arm to go astray (`state_rate`),
after the first missed grasp. Two changes to the candidates, neither of which loosens the guarantee:

- ORs of three: a scene score, a camera score and the arm's own rate; each member at alpha / 3;
- the OR's partners at c = 1, 2 or 4 times their conformal thresholds: a threshold above the conformal one
  alarms on a clean episode no more often, so the OR still keeps alpha, and the partner then fires only far
  outside every successful clean rollout.

For each committed `lerobot-vib-benchmark` output folder the report's failure prediction runs twice on the
same rollouts, with the candidates it offered before (ORs of two, c = 1) and with both changes; each time the
monitor ships by the report's rule on validation rollouts (the earliest among those meeting the TPR, TNR and
benign-stop targets there, else the best balanced accuracy), and its metrics are on the test seeds, which
chose nothing. The RND fitted on clean rollouts needs embeddings, which are not committed; it is left out of
both runs alike (it never ships).

    B=benchmarks/results N=benchmarks/results/tokens_narrow
    python benchmarks/failure_ors.py \
        $B/tokens_act_trunk_l2_s1000_cpu_2core,$B/tokens_act_trunk_l2_3seeds_cpu_2core:vib_tokens_narrow_act_trunk_l2 \
        $B/tokens_act_trunk_l3_2seeds_cpu_2core,$B/tokens_act_trunk_l3_3seeds_cpu_2core:vib_tokens_narrow_act_trunk_l3 \
        ${N}_2seeds_cpu_2core,${N}_3seeds_cpu_2core,${N}_s3000_cpu_2core:vib_tokens_narrow \
        $B/tokens_l2_colour_s1000_cpu_2core:vib_tokens_narrow_act_trunk_l2_colour \
        --output benchmarks/results/failure_ors_cpu_2core/report.md
"""

from __future__ import annotations

from failure_bands import main

from lerobot_vib.failure import THRESHOLDS
from lerobot_vib.scripts.failure_report import OR_MARGINS, OR_SIZES

OFFERED = {
    "ORs of two, at their conformal thresholds (before)": {
        "thresholds": THRESHOLDS, "or_sizes": (2,), "or_margins": (1.0,)
    },
    "ORs of two or three, partners at 1, 2 or 4 times theirs": {
        "thresholds": THRESHOLDS, "or_sizes": OR_SIZES, "or_margins": OR_MARGINS
    },
}  # fmt: skip

if __name__ == "__main__":
    main(OFFERED, "What ORs of three and a margin change in the shipped failure monitor", __file__, __doc__)
