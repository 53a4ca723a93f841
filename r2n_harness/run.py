"""The run harness's hooks into a training script's loop (docs/layout.md, "The run harness's
package"). A script builds a `Run` when one of the flags below is given, and calls it at a few
points: when it opens the run, when it starts or restores it, at each step's start and end, in a
feedback round's teacher, at each evaluation, and when it stops.

- `--resumable`: `state.pt` every `--state-minutes` (or `--checkpoint-freq` steps), on SIGTERM
  and SIGUSR2, and a resume from it (`resume`);
- `--query-log`: every query asked, in `preferences/` (`query_log`);
- `--diagnostics`: the reward's and the input layers' diagnostics (`diagnostics`);
- `--teacher external`: a person's or a program's labels through files (`external_teacher`);
  it turns on the two first;
- `--preferences`: an earlier run's labels as the first pairs of this one (`preferences`).

It reads and changes the run's objects only through what the script hands it: `args`, the
`saved` objects (everything the loop changes, by name), the envs, the writer."""
import os
import signal
import time
from typing import Optional

import torch

from r2n_harness import diagnostics, query_log, resume


def catch_stop_signals() -> list:
    """SIGTERM and SIGUSR2 (SLURM, submitit: preemption, time limit) are noted in the
    returned list; the loop then saves the state at the end of its step and exits."""
    stop_signals = []
    for signum in (signal.SIGTERM, signal.SIGUSR2):
        signal.signal(
            signum, lambda signum, frame: stop_signals.append(signal.Signals(signum).name)
        )
    return stop_signals


class Run:
    """The hooks. `make_run_folder(args)`: the script's own, for a run that does not resume."""

    def __init__(self, args, env, make_run_folder, segment_steps: Optional[int] = None):
        """Open the run: a resume's saved state (`--resumable`, `--run-name`), the check that a
        person's labels are unchanged, an earlier run's labels (`--preferences`). A ValueError
        with one line on bad input, before anything is written. `segment_steps`: the steps of a
        stored query (unset: `--segment-size`; SURF's are longer)."""
        self.segment_steps = segment_steps or getattr(args, "segment_size", None)
        self.args, self.pbrl = args, hasattr(args, "max_feedback")
        self.resume = resume.open_state(args) if args.resumable else None
        self.input_dim = env.observation_space.shape[0] + env.action_space.shape[0]
        self.physics_dim = len(env.physics_state())
        self.obs_dims = env.obs_dim_real, env.observation_space.shape[0]
        self.preferences = None
        if self.pbrl and args.preferences:
            from r2n_harness.preferences import load_preferences

            self.preferences = load_preferences(args.preferences, args.env_id, self.input_dim,
                                                self.segment_steps, args.max_feedback)
        if self.resume and self.pbrl and args.teacher == "external":
            from r2n_harness.external_teacher import check_labels_unchanged

            check_labels_unchanged(f"runs/{args.run_name}", self.resume["objects"]["queries"])
        self.name = args.run_name if self.resume else make_run_folder(args)
        self.folder = f"runs/{self.name}"
        self.state_path = f"{self.folder}/state.pt"
        self.start_step = self.resume["global_step"] if self.resume else None
        suffix = f"/resumed-at-{self.start_step}" if self.resume else ""
        self.video_folder = f"videos/{self.name}{suffix}"
        self.waited = 0.0  # seconds spent waiting for labels: not training time
        self.round_step = None  # the step of a feedback round whose diagnostics are due

    def start(self, saved: dict, envs: list, device: torch.device, writer) -> tuple:
        """Start the run, or continue it from its saved state. It adds the query log to `saved`
        (`--query-log`), so that `state.pt` keeps it. Returns (observation, first step, seconds
        trained)."""
        args = self.args
        self.saved, self.envs, self.device, self.writer = saved, envs, device, writer
        self.external, self.step = None, 0
        self.stop_signals = catch_stop_signals() if args.resumable else []
        if self.pbrl and args.query_log:
            saved["queries"] = query_log.QueryLog(self.segment_steps, self.input_dim,
                                                  self.physics_dim)
        if self.preferences:
            from r2n_harness.preferences import add_preferences

            add_preferences(self.preferences, saved.get("queries"), saved["prefs"], saved["loop"],
                            self.folder, args.env_id, saved["rb"].obs.shape[1], device)
            self.preferences = None
        if self.pbrl and args.teacher == "external":
            from r2n_harness.external_teacher import ExternalTeacher

            self.external = ExternalTeacher(self.folder, args, self.stop_signals, self.stop)
        if self.pbrl and args.diagnostics:  # the buffer's rows behind `pbrl/reward_true_corr`
            generator = torch.Generator().manual_seed(args.seed)
            self.positions = torch.rand(diagnostics.TRANSITIONS, generator=generator).to(device)
        self.last_state = time.monotonic()  # the clock of `--state-minutes`
        if self.resume is None:
            obs, _ = envs[0].reset(seed=args.seed)
            return obs, 0, 0.0
        obs, start_step, elapsed = resume.restore_run(self.resume, saved, envs, args, device,
                                                      writer)
        self.resume = None
        return obs, start_step, elapsed

    def step_starts(self, global_step: int, start_time: float):
        """The labelling page's status of the run (`--teacher external`): its step and training
        time (the waits for labels left out)."""
        self.step = global_step
        if self.external:
            self.external.training(global_step, time.time() - start_time - self.waited)

    def teacher(self, ask):
        """A feedback round's teacher: a person or a program through files (`--teacher
        external`), else `ask`, the script's simulated teacher; each query goes to the query log.
        `shown`: the steps a teacher sees (SURF pads its segments with its crop's steps)."""
        args, loop = self.args, self.saved["loop"]

        def asked(segments, true_rewards, physics, *shown):
            obs_dim, step, sha256 = self.saved["rb"].obs.shape[1], self.step, ""
            if self.external and len(segments):
                cut = shown[0] if shown else slice(None)
                keep, labels, sha256, seconds = self.external.ask(
                    self.saved["queries"].next_round, args.env_id, obs_dim, segments[:, :, cut],
                    true_rewards[:, :, cut], physics[:, :, cut], step, loop.total_feedback,
                    loop.labeled_feedback,
                )
                self.waited += seconds
            else:
                keep, labels = ask(segments, true_rewards, physics, *shown)
            if args.query_log:
                query_log.log_queries(self.saved["queries"], f"{self.folder}/preferences",
                                      args.env_id, obs_dim, segments, true_rewards, physics,
                                      torch.where(keep, labels, torch.nan), step, sha256)
            self.round_step = step
            return keep, labels

        return asked

    def eval_tags(self) -> dict:
        """The input layers' shares of weight on the real features (`--diagnostics`)."""
        if not self.args.diagnostics:
            return {}
        layers = diagnostics.input_layers(self.saved["agent"])
        if self.pbrl:
            layers |= {f"reward{i}": weight
                       for i, weight in enumerate(self.saved["reward_model"].weights[0])}
        return diagnostics.weight_shares(layers, *self.obs_dims)

    def step_ends(self, global_step: int, obs: torch.Tensor, start_time: float,
                  round_next: bool = False):
        """After a step: a feedback round's diagnostics (`--diagnostics`); `state.pt` when due,
        at a stop signal, and before a person's round (`round_next`), so that a resume goes back
        into it."""
        args, saved = self.args, self.saved
        if self.round_step is not None and args.diagnostics:
            step = self.round_step
            self.writer.add_scalar("pbrl/reward_steps",
                                   diagnostics.optimizer_steps(saved["reward_optimizer"]), step)
            diagnostics.log_reward_diagnostics(
                self.writer, step, args.seed, saved["reward_model"], saved["rb"],
                saved["episodes"], self.positions, diagnostics.PAIRS, args.segment_size)
        self.round_step = None
        if not args.resumable:
            return
        if self.stop_signals or resume.state_due(global_step, args, self.last_state) or (
            self.external and round_next
        ):
            resume.save_state(self.state_path, args, global_step,
                              time.time() - start_time - self.waited, obs, saved, self.device,
                              self.envs, self.writer)
            self.last_state = time.monotonic()
            if self.stop_signals:
                raise self.stop(f"stopped by {self.stop_signals[0]} after step {global_step + 1}; "
                                f"state saved in {self.state_path}: run the same command with "
                                f"--run-name {self.name} to resume")

    def stop(self, message: str) -> SystemExit:
        """The exit of a stopped run (a stop signal, a non-finite value): the labelling page is
        told, the writer closed."""
        if self.external:
            loop = self.saved["loop"]
            self.external.tell("stopped", self.step, loop.total_feedback,
                               loop.labeled_feedback, message=message)
        self.writer.close()
        return SystemExit(f"{self.args.exp_name}: {message}")

    def finish(self):
        """The run is complete: the labelling page is told; `state.pt` is deleted (unless
        `--keep-state`), last, so that a kill before it leaves a state to resume."""
        if self.external:
            loop = self.saved["loop"]
            self.external.tell("finished", self.args.total_timesteps, loop.total_feedback,
                               loop.labeled_feedback)
        if not self.args.keep_state and os.path.exists(self.state_path):
            os.remove(self.state_path)
