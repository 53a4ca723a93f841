"""The run harness of the R2N scripts: what a method file needs only under the flag that asks for it.

Each training script holds its method whole and runs it with its default flags without this package. A flag that
needs more imports its module here inside its own branch, as CleanRL's scripts import `cleanrl_utils`:
- `run`: the hooks a script calls under any of the flags below (`Run`);
- `resume`: `--resumable`, the training state `state.pt` and an exact resume from it;
- `query_log`: `--query-log`, every query asked, in the run's `preferences/`;
- `diagnostics`: `--diagnostics`, how well the reward tracks the true one, and the input layers' weight on features;
- `external_teacher`: `--teacher external`, queries and labels through files (the labelling page's protocol);
- `preferences`: `--preferences`, an earlier run's query log as this run's first labelled pairs;
- `cuda_graph`: `--cuda-graph`, the SAC steps replayed as CUDA graphs (`--cuda-graph-whole`: the whole update).
A module reads and changes a run's objects only through what the script hands it (docs/layout.md).
"""
