"""The run harness of the R2N scripts: what a method file needs only under the flag that asks for it.

Each training script holds its method whole and runs it with its default flags without this package. A flag that
needs more imports its module here inside its own branch, as CleanRL's scripts import `cleanrl_utils`:
- `cuda_graph`: `--cuda-graph`, the SAC steps replayed as CUDA graphs;
- `external_teacher`: `--teacher external`, queries and labels through files (the labelling page's protocol);
- `preferences`: `--preferences`, an earlier run's query log as this run's first labelled pairs.
A module reads and changes a run's objects only through what the script hands it (docs/layout.md).
"""
