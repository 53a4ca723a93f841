"""Tests import the scripts as modules (their side effects live under `if __name__ == "__main__":`)."""
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
os.environ.setdefault("OMP_NUM_THREADS", "1")

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)

# dm_control logs through absl, whose handler keeps the sys.stderr it saw when imported and closes it when the handler
# is closed (submitit sets up its logging with dictConfig, which closes every handler). Point it at the real stderr,
# which it never closes, so it cannot close pytest's capture stream.
import absl.logging  # noqa: E402

absl.logging.get_absl_handler().python_handler.stream = sys.__stderr__


# Under pytest-xdist (`-n auto --dist loadgroup`, the README's command), tests that share an expensive module fixture
# run on one worker, so that the fixture's runs are made once. Every other test goes to whichever worker is free.
SHARED_FIXTURES = ("pipeline", "smoke_runs", "synthetic")


def pytest_collection_modifyitems(items):
    for item in items:
        for fixture in SHARED_FIXTURES:
            if fixture in getattr(item, "fixturenames", ()):
                item.add_marker(pytest.mark.xdist_group(fixture))
