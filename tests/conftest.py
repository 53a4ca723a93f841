"""Tests import the scripts as modules (their side effects live under `if __name__ == "__main__":`)."""
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

torch.set_num_threads(1)

# dm_control logs through absl, whose handler keeps the sys.stderr it saw when imported and closes it when the handler
# is closed (submitit sets up its logging with dictConfig, which closes every handler). Point it at the real stderr,
# which it never closes, so it cannot close pytest's capture stream.
import absl.logging  # noqa: E402

absl.logging.get_absl_handler().python_handler.stream = sys.__stderr__

