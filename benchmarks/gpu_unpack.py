"""Join what `benchmarks/gpu_train.sh` brought back into a loadable checkpoint.

    python benchmarks/gpu_unpack.py <folder with NAME_ckpt.tar.gz, NAME_model/ema.safetensors> NAME OUT_DIR

OUT_DIR gets the checkpoint's folder as LeRobot saved it: pretrained_model/ (config, processors, the joined
model.safetensors) and training_state/ (without the optimizer, which did not travel).
"""

from __future__ import annotations

import re
import sys
import tarfile
from pathlib import Path

from safetensors.torch import load_file, save_file


def unpack(src: Path, name: str, out: Path) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    with tarfile.open(src / f"{name}_ckpt.tar.gz") as tar:
        tar.extractall(out, filter="data")
    state = {**load_file(str(src / f"{name}_model.safetensors")), **load_file(str(src / f"{name}_ema.safetensors"))}
    model = out / "pretrained_model"
    save_file(state, str(model / "model.safetensors"))
    # Evaluated where it lands (a CPU machine): the configs and the device step name the GPU it trained on.
    for name in ("config.json", "train_config.json", "policy_preprocessor.json", "policy_postprocessor.json"):
        path = model / name
        if path.is_file():
            path.write_text(re.sub(r'"device": "cuda(:\d+)?"', '"device": "cpu"', path.read_text()))
    return model


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    print(unpack(Path(sys.argv[1]), sys.argv[2], Path(sys.argv[3])))
