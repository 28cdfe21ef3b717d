"""The training loop's time budget (BudgetFit, TimeLimit) and the schedule it refits (StepDrop)."""

from __future__ import annotations

import json

import pytest
import torch

from comgrasp_train.models.vq_losses import StepDrop
from comgrasp_train.train.runtime import BudgetFit, Runtime, TimeLimit, run_training


class FakeClock:
    def __init__(self, step_seconds: float):
        self.t, self.step_seconds = 0.0, step_seconds

    def __call__(self) -> float:
        return self.t

    def tick(self, seconds: float | None = None) -> None:
        self.t += self.step_seconds if seconds is None else seconds


def test_budget_fit_sets_the_end_from_the_measured_step_time_and_stops_when_spent():
    clock = FakeClock(0.5)
    fit = BudgetFit(100.0, step0=10, clock=clock)
    end, step = 10**6, 10
    clock.tick(3.0)  # the first steps are slow (allocation, kernel selection): not measured
    for _ in range(BudgetFit.WARM + BudgetFit.CALIBRATE):
        step += 1
        end = fit.after_step(step, end)
        clock.tick()
    # steps 5..25 timed at 0.5 s each; 15 s spent, so 85 s left at 0.5 s/step with 10% kept
    # back: 153 more steps
    assert fit.fitted and end == step + 153
    # a step that suddenly takes the rest of the budget ends the run at that step
    clock.tick(90.0)
    assert fit.after_step(step + 1, end) == step + 1


def test_budget_fit_rejects_a_budget_that_is_not_positive():
    for bad in (0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="positive"):
            BudgetFit(bad, 0)


def test_step_drop_total_travels_with_the_scheduler_state():
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, StepDrop(10, 300))
    sched.lr_lambdas[0].total = 90  # as a fitted run sets it
    state = sched.state_dict()
    opt2 = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    sched2 = torch.optim.lr_scheduler.LambdaLR(opt2, StepDrop(10, 300))
    sched2.load_state_dict(state)
    assert sched2.lr_lambdas[0].total == 90
    assert sched2.lr_lambdas[0](59) == 1.0 and sched2.lr_lambdas[0](60) == 0.05  # drop at 2/3 of 90


@pytest.mark.parametrize("limit", ["seconds", "deadline"])
def test_run_training_fits_its_length_schedule_and_config_to_the_budget(tmp_path, limit):
    import time

    time_limit = TimeLimit(seconds=0.5) if limit == "seconds" else TimeLimit(deadline=time.time() + 0.5)
    model = torch.nn.Linear(2, 1)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, StepDrop(1000, 10**6))
    config = {"train": {"total_iters": 10**6, "warmup_iters": 1000}}
    steps = []

    def step_fn():
        steps.append(len(steps))
        opt.step()
        sched.step()
        return {"loss": 0.0}

    run_training(Runtime(torch.device("cpu")), step=0, end=10**6, total=10**6, desc="t", step_fn=step_fn,
                 out_dir=tmp_path, model=model, optimizer=opt, scheduler=sched, config=config,
                 gen=torch.Generator(), log_every=10**6, ckpt_every=10**6, progress=False, time_limit=time_limit)
    n = len(steps)
    assert BudgetFit.WARM + BudgetFit.CALIBRATE < n < 10**6
    # the schedule, the config beside the checkpoint and the checkpoint agree on the length
    assert sched.lr_lambdas[0].total == n == config["train"]["total_iters"]
    assert sched.lr_lambdas[0].warmup == min(1000, max(1, n // 10)) == config["train"]["warmup_iters"]
    saved = json.loads((tmp_path / "config.json").read_text())
    assert saved["train"]["total_iters"] == n
    # what the loop was given: the seconds, or what was left of the deadline when it started
    assert (saved["time_budget_s"] == 0.5) if limit == "seconds" else (0 < saved["time_budget_s"] < 0.5)
    assert torch.load(tmp_path / "ckpt.pt", weights_only=False)["step"] == n


def test_time_limit_by_deadline_counts_the_loading_before_the_loop():
    assert TimeLimit(seconds=30.0).budget(now=1e9) == 30.0
    assert TimeLimit(deadline=1000.0).budget(now=940.0) == 60.0  # the loop gets what loading left
    with pytest.raises(ValueError, match="deadline passed 5 s before training started"):
        TimeLimit(deadline=1000.0).budget(now=1005.0)
    for bad in ({}, {"seconds": 1.0, "deadline": 2.0}):
        with pytest.raises(ValueError, match="exactly one"):
            TimeLimit(**bad)
