"""Where the compiled SpoilDICE + weighted-BC step spends its time: a profiler trace of the update, per kernel.

    python benchmarks/profile_step.py                      # both penalty forms, one thread, 50 steps each
    python benchmarks/profile_step.py --forms relu_chain --steps 100 --top 30

For each gradient-penalty form (``train.penalty_form``) the bench's step is compiled, warmed up, then profiled
with ``torch.profiler`` and Inductor's per-kernel profiling on (through Inductor's Python wrapper, whose calls the
profiler sees; the step's default on a CPU is the C++ wrapper, with the same kernels). It prints milliseconds per
step in:

* products: the matrix products (``aten::mm`` / ``addmm``, MKL or oneDNN), listed by shape with their FLOPs, so
  the products of the penalty's points (1,536 rows at the bench's sizes), of the initial and next states (1,024),
  of the batch (512) and the weight gradients (the rows as the inner dimension) can be told apart;
* elementwise: Inductor's generated C++ kernels (activations, masks, the losses, reductions, fused);
* optimiser: Adam (PyTorch's fused kernel once the step is compiled);
* the rest of the step's wall time: Python, the dispatcher, Dynamo's guards, the tensordict reads and the
  penalty points' random draws outside the graph.

Then, without the trace and with the step's default wrapper, the step's parts in milliseconds: the parameters
(read once and kept), the inputs (reads and the penalty's draws), the compiled graph's call, the gradients handed
to the three Adam steps, the outputs.

With ``--peer`` (the ``bench`` extra installed), the JAX peer's step (``jax_peer.py``) is traced the same way
with XLA's own profiler (``jax.profiler``): milliseconds per step in each operation of its compiled program, in
three groups: products (XLA's ``dot`` instructions and the YNNPACK fusions built around one), its other fusions
(elementwise, reductions, its Adam) and copies. XLA's trace slows its step far more than PyTorch's does (its
traced and untraced step times are printed): read the peer's lines as shares, not times.

The trace slows the step down a little; the shares are what it is for. Timings on shared 2-core machines vary by
30-50 % between runs: compare forms within one run.
"""

from __future__ import annotations

import argparse
import collections
import re
import tempfile
import time
from pathlib import Path

import torch
import torch._inductor.config as inductor_config
from bench_losses import CompiledLibraryStep, make_batch, rate

from spoil_torchrl.precision import matmul_precision

PRODUCTS = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm")


def _flops(name: str, shapes: list) -> float:
    """2 M N K of a product event from its recorded input shapes."""
    try:
        if name == "aten::addmm":
            (m, k), (_, n) = shapes[1], shapes[2]
        else:
            (m, k), (_, n) = shapes[0], shapes[1]
    except (ValueError, IndexError, TypeError):
        return 0.0
    return 2.0 * m * n * k


def profile(form: str, steps: int, precision: str, batches) -> tuple[dict, list, float]:
    """Milliseconds per step by category, the products by shape, and the step's wall time (ms) under the trace."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    # Inductor's Python wrapper: the C++ one (the default on a CPU) calls the products past the profiler. The
    # kernels are the same (bit for bit), the wrapper's own time is not.
    step = CompiledLibraryStep(28, 2, (256, 256), penalty_form=form, mode="default")
    with matmul_precision(precision):
        # each generated kernel its own profiler event: compiled in, so only for this traced step
        with inductor_config.patch({"cpp.enable_kernel_profile": True}):
            rate(step, batches, 20)  # compiles, warms up
        with torch_profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            start = time.perf_counter()
            rate(step, batches, steps)
            wall = (time.perf_counter() - start) * 1e3 / steps
    categories: dict[str, float] = collections.Counter()
    products: dict[tuple, list] = {}
    for event in prof.key_averages(group_by_input_shape=True):
        ms = event.self_cpu_time_total / 1e3 / steps
        if event.key in PRODUCTS:
            categories["products"] += ms
            shapes = [tuple(s) for s in event.input_shapes if s]
            entry = products.setdefault((event.key, str(shapes)), [0.0, 0, _flops(event.key, shapes)])
            entry[0] += ms
            entry[1] += event.count // steps
        elif "cpp_fused" in event.key:
            categories["elementwise (Inductor kernels)"] += ms
        elif "adam" in event.key.lower() and event.key.startswith("aten::"):
            categories["optimiser (Adam)"] += ms
    categories["the rest (Python, dispatcher, guards, draws)"] = wall - sum(categories.values())
    table = sorted(((ms, calls, flops, key) for key, (ms, calls, flops) in products.items()), reverse=True)
    return dict(categories), table, wall


def outside_graph(form: str, steps: int, precision: str, batches) -> dict[str, float]:
    """Milliseconds per step, without the trace, of each part of :meth:`CompiledStepper.step`: the parts around
    the compiled graph (parameters, inputs and the penalty's draws, gradients handed over, the three Adam steps,
    the outputs' tensordict) and the graph's own call (guards, Inductor's wrapper, the kernels)."""
    from spoil_torchrl.trainers.compiled import scalar_outputs, set_gradients, step_inputs

    stepper = CompiledLibraryStep(28, 2, (256, 256), penalty_form=form).stepper
    parts: dict[str, float] = collections.Counter()
    clock = time.perf_counter
    with matmul_precision(precision):
        for i in range(20):  # compiles, warms up
            stepper.step(None, batches[i % len(batches)])
        for i in range(steps):
            t0 = clock()
            parameters, plain = stepper._parameters  # read once, kept from step to step
            t1 = clock()
            inputs = step_inputs(stepper.losses, stepper._earlier, batches[i % len(batches)])
            t2 = clock()
            grads, (_, outputs) = stepper._fn(plain, inputs)
            t3 = clock()
            set_gradients(parameters, grads)
            stepper._step_optimizers()  # the fused Adam kernel called straight, as the stepper does
            set_gradients(parameters, None)
            t4 = clock()
            scalar_outputs(outputs)
            t5 = clock()
            for name, seconds in (
                ("parameters", t1 - t0),
                ("inputs (reads, penalty draws)", t2 - t1),
                ("compiled graph (guards, wrapper, kernels)", t3 - t2),
                ("gradients handed over, Adam x 3, dropped", t4 - t3),
                ("outputs (tensordict)", t5 - t4),
            ):
                parts[name] += 1e3 * seconds / steps
    return dict(parts)


def xla_operations(hlo: str) -> dict[str, tuple[str, str]]:
    """The operations of an optimised HLO module's entry computation: name -> (group, output shape); a fusion
    whose computation holds a ``dot`` counts as a product.

    >>> module = '''%fused_computation.1 (p: f32[4,2]) -> f32[4,4] {
    ...   ROOT %d = f32[4,4]{1,0} dot(%p, %p), lhs_contracting_dims={1}, rhs_contracting_dims={1}
    ... }
    ...
    ... ENTRY %main (x: f32[4,2]) -> f32[4,4] {
    ...   %x = f32[4,2]{1,0} parameter(0)
    ...   %copy.1 = f32[4,2]{0,1} copy(%x)
    ...   ROOT %ynn_fusion = f32[4,4]{1,0} fusion(%copy.1), kind=kCustom, calls=%fused_computation.1
    ... }'''
    >>> xla_operations(module)
    {'copy.1': ('copies', 'f32[4,2]'), 'ynn_fusion': ('products', 'f32[4,4]')}
    """
    bodies: dict[str, str] = {}
    for block in re.split(r"\n(?=%|ENTRY)", hlo):
        header = re.match(r"(?:ENTRY )?%([\w.\-]+)", block)
        if header:
            bodies["ENTRY" if block.startswith("ENTRY") else header.group(1)] = block
    operations = {}
    for line in bodies.get("ENTRY", "").splitlines():
        found = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = (\w+\[[\d,]*\])\S* (\w+)\(", line)
        if not found or found.group(3) in ("parameter", "constant", "tuple", "get-tuple-element", "bitcast"):
            continue
        name, shape, op = found.groups()
        called = re.search(r"calls=%([\w.\-]+)", line)
        if op == "dot" or (op == "fusion" and called and " dot(" in bodies.get(called.group(1), "")):
            group = "products"
        elif op in ("copy", "transpose"):
            group = "copies"
        else:
            group = "other operations (elementwise, reductions, Adam, loops)"
        operations[name] = (group, shape)
    return operations


def peer_profile(jax, steps: int, batches) -> tuple[dict, list, float, float]:
    """The JAX peer's step under XLA's profiler: milliseconds per step by group and per operation (with its
    output shape), the traced step's wall time and the untraced one (ms)."""
    from jax.profiler import ProfileData
    from jax_peer import JaxStep, jax_rate

    peer = JaxStep(28, 2, (256, 256))
    peer_batches = [peer.batch(b) for b in batches]
    jax_rate(peer, peer_batches, 20)  # compiles, warms up
    untraced = 1e3 / jax_rate(peer, peer_batches, steps)
    with tempfile.TemporaryDirectory() as folder:
        jax.profiler.start_trace(folder)
        start = time.perf_counter()
        jax_rate(peer, peer_batches, steps)
        wall = (time.perf_counter() - start) * 1e3 / steps
        jax.profiler.stop_trace()
        data = ProfileData.from_file(str(next(Path(folder).rglob("*.xplane.pb"))))
    operations = xla_operations(peer.compiled(peer_batches[0]).as_text())
    per_operation: dict[str, float] = collections.Counter()
    for plane in data.planes:
        for line in plane.lines:
            for event in line.events:
                if event.name in operations:  # XLA runs independent operations on two threads: both count
                    per_operation[event.name] += event.duration_ns / 1e6 / steps
    groups: dict[str, float] = collections.Counter()
    for name, ms in per_operation.items():
        groups[operations[name][0]] += ms
    table = sorted(((ms, name, *operations[name]) for name, ms in per_operation.items()), reverse=True)
    return dict(groups), table, wall, untraced


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--forms", nargs="+", default=["autograd", "relu_chain"])
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--precision", default="highest", help="float32 matmul precision (highest: MKL)")
    parser.add_argument("--top", type=int, default=12, help="products listed per form")
    parser.add_argument("--peer", action="store_true", help="also the JAX peer under XLA's profiler")
    args = parser.parse_args()
    jax = None
    if args.peer:
        from jax_peer import import_jax

        jax = import_jax(args.threads)  # before torch runs anything: XLA reads its threads on import
        if jax is None:
            raise SystemExit('--peer needs JAX: pip install -e ".[bench]"')
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    batches = [make_batch(512, 512, 28, 2) for _ in range(8)]
    for form in args.forms:
        categories, table, wall = profile(form, args.steps, args.precision, batches)
        print(
            f"penalty_form={form}: {wall:.1f} ms per step under the trace ({args.threads} thread(s), "
            f"matmul precision {args.precision})"
        )
        for name, ms in categories.items():
            print(f"  {name:<46} {ms:7.2f} ms  {100 * ms / wall:5.1f} %")
        parts = outside_graph(form, args.steps, args.precision, batches)
        print(f"  without the trace: {sum(parts.values()):.1f} ms per step")
        for name, ms in parts.items():
            print(f"    {name:<44} {ms:7.2f} ms")
        print(f"  products by shape (top {args.top}):")
        for ms, calls, flops, (name, shapes) in table[: args.top]:
            rate_gflops = calls * flops / (ms / 1e3) / 1e9 if ms > 0 else 0.0
            print(f"    {ms:6.2f} ms  {calls} x {name:<11} {shapes:<48} {rate_gflops:5.0f} GFLOP/s")
    if jax is not None:
        groups, table, wall, untraced = peer_profile(jax, args.steps, batches)
        print(
            f"JAX peer: {wall:.1f} ms per step under XLA's trace, {untraced:.1f} ms without it; milliseconds per "
            "step under the trace:"
        )
        for name, ms in sorted(groups.items(), key=lambda kv: -kv[1]):
            print(f"  {name:<58} {ms:7.2f} ms  {100 * ms / sum(groups.values()):5.1f} %")
        print(f"  operations (top {args.top}):")
        for ms, name, group, shape in table[: args.top]:
            print(f"    {ms:6.2f} ms  {name:<32} {shape:<16} {group.split(' ')[0]}")


if __name__ == "__main__":
    main()
