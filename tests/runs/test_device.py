"""``device=``: every tensor a run's stages hold lives on the configured device, and no training step moves data
between devices or reads a value back to the host (on CPU here; on CUDA too where a GPU is present)."""

from __future__ import annotations

import collections
import traceback
from pathlib import Path

import pytest
import torch
from tensordict import TensorDictBase
from torch.overrides import TorchFunctionMode

from spoil_torchrl.algorithms import ALGORITHMS
from spoil_torchrl.devices import training_device
from spoil_torchrl.errors import SettingsError
from spoil_torchrl.runs.lifecycle import claim_runs, open_runs, pretrain
from spoil_torchrl.runs.seed_run import rollout_job
from spoil_torchrl.runs.settings import check_settings
from spoil_torchrl.runs.training import one_seed
from spoil_torchrl.trainers import offline_trainer
from tests.short_runs import composed_settings

DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU")),
]

#: Tensor methods that read a value back to the host (a synchronisation on a GPU).
READS = {"item", "tolist", "numpy", "__bool__", "__float__", "__int__", "__index__"}


class Transfers(TorchFunctionMode):
    """Counts, by where they were called from, the host reads (:data:`READS`) and the moves of a tensor to
    another device than its own (``to`` / ``cpu`` / ``cuda``). torch.optim's own reads of its step counters,
    which PyTorch keeps on the host for every device, are not counted."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: collections.Counter = collections.Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        counted = name in READS or (name in ("to", "cpu", "cuda") and _moves(name, args, kwargs))
        if counted:
            frames = traceback.extract_stack()[:-1]
            if not any("torch/optim/" in f.filename for f in frames):
                where = " <- ".join(f"{Path(f.filename).name}:{f.lineno}" for f in reversed(frames[-4:]))
                self.calls[f"{name} @ {where}"] += 1
        return func(*args, **kwargs)


def _moves(name: str, args, kwargs) -> bool:
    """Whether ``tensor.<name>(...)`` puts the tensor on another device than its own."""
    tensor = args[0] if args else None
    if not isinstance(tensor, torch.Tensor):
        return False
    if name == "cpu":
        return tensor.device.type != "cpu"
    if name == "cuda":
        return tensor.device.type != "cuda"
    target = kwargs.get("device")
    for arg in args[1:]:
        if isinstance(arg, (str, torch.device)):
            target = arg
        elif isinstance(arg, torch.Tensor):
            target = arg.device
    return target is not None and torch.device(target) != tensor.device


def _tensors(value, where: str):
    """Every tensor in ``value`` (tensordicts, modules, mappings, sequences, dataclass-like objects), named."""
    if isinstance(value, torch.Tensor):
        yield where, value
    elif isinstance(value, TensorDictBase):
        for key, leaf in value.items(include_nested=True, leaves_only=True):
            yield f"{where}[{key}]", leaf
    elif isinstance(value, torch.nn.Module):
        yield from _tensors(value.state_dict(keep_vars=True), where)
    elif isinstance(value, torch.optim.Optimizer):
        for i, group in enumerate(value.param_groups):
            for j, p in enumerate(group["params"]):
                yield f"{where}.param[{i}][{j}]", p
                for key, state in value.state.get(p, {}).items():
                    if key != "step":  # Adam's step counter: on the host unless fused or capturable
                        yield from _tensors(state, f"{where}.state[{i}][{j}].{key}")
    elif isinstance(value, collections.abc.Mapping):
        for key, item in value.items():
            yield from _tensors(item, f"{where}.{key}")
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            yield from _tensors(item, f"{where}[{i}]")


def _held(run) -> dict[str, torch.Tensor]:
    """Every tensor a pre-trained run's stages hold: buffers, losses, optimisers, annotations, the DICE
    diagnostics' probe, the observation statistics and the evaluated policy."""
    buffers, training = run.inputs.buffers, run.training
    held = dict(_tensors({role: buffers[role].storage[:] for role in buffers.roles}, "buffers"))
    stepper = training.stepper
    held.update(_tensors(dict(stepper.losses), "losses"))
    held.update(_tensors(list(getattr(stepper, "optimizers", [])), "optimizers"))
    held.update(_tensors(dict(run.pretraining.annotations), "pretraining.annotations"))
    if run.probe is not None:
        probe = run.probe
        held.update(_tensors([probe.transitions, probe.initial, dict(probe.pools or {})], "probe"))
    if training.observation_norm is not None:
        held.update(_tensors(training.observation_norm, "observation_norm"))
    held.update(_tensors(rollout_job(run).args[0], "evaluated policy"))
    return held


def test_a_device_that_is_not_there_or_not_a_device_is_one_clear_line():
    with pytest.raises(SettingsError, match="expected cpu or cuda"):
        check_settings({"device": "gpu"})
    with pytest.raises(SettingsError, match="expected cpu or cuda"):
        check_settings({"device": "tpu"})
    assert training_device(None) == torch.device("cpu")
    if not torch.cuda.is_available():
        with pytest.raises(SettingsError, match="no CUDA device"):
            check_settings({"device": "cuda"})


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(
    "algo, compiled",
    [
        *((algo, False) for algo in ALGORITHMS),
        pytest.param("spoildice", True, marks=pytest.mark.compiles),
    ],
)
def test_every_stage_holds_its_tensors_on_the_device_and_no_step_moves_data(
    tmp_path, tiny_pc1_dataset, device, algo, compiled
):
    cfg = composed_settings(
        tiny_pc1_dataset,
        f"algo={algo}",
        f"device={device}",
        "train.batch_size=64",
        "train.checkpoint=false",
        f"train.compile={str(compiled).lower()}",
    )
    with claim_runs(cfg, tmp_path) as claim:
        run = pretrain(open_runs(claim)[0])
        steps = one_seed(run)
        for _ in range(2):  # every optimiser state made (and a compiled step compiled) before it is examined
            steps.stepper.step(None, steps.sample())
        on = torch.empty(0, device=training_device(device)).device  # "cuda" as its tensors report it: cuda:0
        elsewhere = {name: str(t.device) for name, t in _held(run).items() if t.device != on}
        assert not elsewhere, elsewhere
        assert all(g.device == on for g in run.inputs.buffers._generators.values())

        # the main stage's Trainer, one chunk of n steps: what it reads back is per chunk, never per step
        counts = {}
        for n in (4, 8):
            trainer = offline_trainer(
                steps.stepper, steps.sample, total_steps=n, steps_per_batch=n, progress_bar=False
            )
            with Transfers() as transfers:
                trainer.train()
            counts[n] = transfers.calls
        assert counts[4] == counts[8], (counts[4], counts[8])
        with Transfers() as transfers:  # and a step alone reads and moves nothing
            for _ in range(3):
                steps.stepper.step(None, steps.sample())
        assert not transfers.calls, dict(transfers.calls)


def test_the_counter_sees_a_step_that_reads_back(tmp_path):
    """The check above can fail: a value read back per step is counted, a host-side optimiser's is not."""
    p = torch.nn.Parameter(torch.ones(3))
    opt = torch.optim.Adam([p], lr=0.1)
    with Transfers() as transfers:
        for _ in range(3):
            loss = (p**2).sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
            float(loss)  # a read per step
            p.detach().to(torch.float64)  # a cast on the same device is no move
    assert sum(transfers.calls.values()) == 3 and all(k.startswith("__float__") for k in transfers.calls)
