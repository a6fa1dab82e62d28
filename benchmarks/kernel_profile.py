"""Kernel-by-kernel profiles of compiled JAX programs, shared by ``drqv2_profile.py`` and ``sac_profile.py``.

A compiled program runs under ``jax.profiler.trace`` (:func:`trace`); the trace's events that carry an ``hlo_op``
of the program's HLO module (on the GPU the kernels of the device plane's streams, on the CPU the host's thunks)
are read with ``jax.profiler.ProfileData`` (:func:`trace_events`) and summed per HLO instruction (:func:`summarize`).
Each instruction is put in a category read from the compiled HLO text (:func:`categories`: the cuDNN convolutions by
direction, matrix products, fusions by kind, the rest by opcode) and, optionally, in a part of the program read from
the Python call stack XLA keeps for it (:func:`call_stacks`, :func:`parts`: e.g. the physics, the optimiser). The
matrix products' FLOPs are counted from the same text (:func:`dot_flops`).

XLA's command buffers (CUDA graphs) are traced as one event each, named ``command_buffer_<n>``, and counted as
"not in the HLO"; ``--xla-flags=--xla_gpu_enable_command_buffer=`` turns them off, so that their kernels are traced
one by one.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import math
import pathlib
import re
import tempfile
import time
from collections.abc import Callable, Iterable
from typing import Any

import jax

NOT_IN_HLO = "not in the HLO"
OTHER = "other"
NO_STACK = "XLA's own (no call stack)"
_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*(.*)$")
_OPCODE = re.compile(r"(?:^|\s)([a-z][a-z0-9\-]*)\(")
_TARGET = re.compile(r'custom_call_target="([^"]+)"')
_KIND = re.compile(r"kind=(k\w+)")
_SHAPE = re.compile(r"[a-z]+\d*\[([\d,]*)\]")
_OPERAND = re.compile(r"\s*(?:([a-z]+\d*\[[\d,]*\])\S*\s+)?%?([\w.\-]+)")
_FRAME_ID = re.compile(r"stack_frame_id=(\d+)")
_FIELDS = re.compile(r"(\w+)=(\d+)")
CONVOLUTIONS = {
    "convForward": "convolution forward",
    "convBiasActivationForward": "convolution forward",
    "convBackwardInput": "convolution input gradient",
    "convBackwardFilter": "convolution kernel gradient",
}
GEMM_TARGETS = ("gemm", "matmul")  # __cublas$gemm, __cublas$lt$matmul, __onednn$matmul ...


def _opcode(rest: str) -> str:
    opcode = _OPCODE.search(rest)
    return opcode.group(1) if opcode else "unknown"


def category(rest: str) -> str:
    """The category of one HLO instruction from the text after its ``=`` (shape, opcode, operands, attributes)."""
    opcode = _opcode(rest)
    if opcode == "custom-call":
        target = _TARGET.search(rest)
        target = target.group(1) if target else ""
        for name, label in CONVOLUTIONS.items():
            if target.endswith(name):
                return label
        if any(name in target for name in GEMM_TARGETS):
            return "matrix product"
        return f"custom-call {target}"
    if opcode == "convolution":
        return "convolution (XLA)"
    if opcode in ("dot", "cublas-gemm"):
        return "matrix product"
    if opcode == "fusion":
        if "triton_gemm" in rest:
            return "matrix product"
        kind = _KIND.search(rest)
        return f"fusion {kind.group(1) if kind else ''}".strip()
    return opcode


def instructions(hlo: str) -> dict[str, str]:
    """HLO instruction name -> the text after its ``=``, for every instruction of every computation of ``hlo``."""
    found = {}
    for line in hlo.splitlines():
        match = _INSTRUCTION.match(line)
        if match:
            found[match.group(1)] = match.group(2)
    return found


def categories(hlo: str) -> dict[str, str]:
    """HLO instruction name -> :func:`category`, for every instruction of every computation of ``hlo``'s text."""
    return {name: category(rest) for name, rest in instructions(hlo).items()}


def module_name(hlo: str) -> str:
    """The name of the HLO module of ``hlo``'s text (``HloModule jit_many, ...`` -> ``jit_many``)."""
    match = re.search(r"^HloModule ([\w.\-]+)", hlo, re.MULTILINE)
    if not match:
        raise ValueError("not the text of an HLO module: no 'HloModule' line")
    return match.group(1)


def _dims(shape: str) -> list[int]:
    match = _SHAPE.search(shape)
    return [int(d) for d in match.group(1).split(",") if d] if match else []


def dot_flops(hlo: str) -> float:
    """FLOPs of the matrix products of ``hlo``'s text: ``2 * prod(output dims) * prod(contracted dims)`` for every
    ``dot`` (fused or not) and every GEMM library call, each instruction counted once (a loop body's once, not once
    per trip). The contracted sizes are read from the left operand's shape (``lhs_contracting_dims``), or for a
    library call from its ``backend_config`` (``lhs_contracting_dimensions``)."""
    found = instructions(hlo)
    total = 0.0
    for rest in found.values():
        opcode = _opcode(rest)
        target = _TARGET.search(rest)
        gemm = opcode == "custom-call" and target and any(name in target.group(1) for name in GEMM_TARGETS)
        if opcode != "dot" and not gemm:
            continue
        out = _dims(rest.lstrip("("))  # a library call's result is a (product, workspace) tuple
        contracting = re.search(r"lhs_contracting_dim\w*\W+([\d,\"\s]*)", rest)
        contracting = [int(d) for d in re.findall(r"\d+", contracting.group(1))] if contracting else []
        operands = rest[rest.index(opcode + "(") + len(opcode) + 1 :]
        lhs = _OPERAND.match(operands)  # ``f32[2,3]{1,0} %a, ...`` or ``%a, ...``
        lhs_shape = _dims(lhs.group(1)) if lhs.group(1) else _dims(found.get(lhs.group(2), ""))
        total += 2.0 * math.prod(out) * math.prod(lhs_shape[d] for d in contracting)
    return total


@dataclasses.dataclass(frozen=True)
class Frame:
    """One Python frame of the call stack XLA keeps for an instruction."""

    file: str
    function: str
    line: int


def _section(hlo: str, name: str) -> list[str]:
    """The lines of one of the module's trailing tables (``FileNames``, ``StackFrames``, ...)."""
    match = re.search(rf"^{name}\n(.*?)(?:\n\n|\Z)", hlo, re.MULTILINE | re.DOTALL)
    return match.group(1).splitlines() if match else []


def _table(hlo: str, name: str) -> dict[int, str]:
    return {int(line.split(None, 1)[0]): line.split(None, 1)[1] for line in _section(hlo, name) if line.strip()}


def call_stacks(hlo: str) -> dict[str, tuple[Frame, ...]]:
    """HLO instruction name -> the Python call stack it was traced from, innermost frame first, for every
    instruction whose metadata has a ``stack_frame_id``.

    The stacks come from the tables XLA prints after the computations: ``FileNames``, ``FunctionNames``,
    ``FileLocations`` and ``StackFrames`` (each ``id {file_location_id=L parent_frame_id=P}``, where ``P - 1`` is
    the id of the caller's frame and 0 none, as jaxlib 0.10.2's XLA prints them).
    """
    files = {i: text.strip('"') for i, text in _table(hlo, "FileNames").items()}
    functions = {i: text.strip('"') for i, text in _table(hlo, "FunctionNames").items()}
    locations = {}
    for i, text in _table(hlo, "FileLocations").items():
        fields = {k: int(v) for k, v in _FIELDS.findall(text)}
        locations[i] = Frame(files[fields["file_name_id"]], functions[fields["function_name_id"]], fields["line"])
    parents = {}
    for i, text in _table(hlo, "StackFrames").items():
        fields = {k: int(v) for k, v in _FIELDS.findall(text)}
        parents[i] = (locations[fields["file_location_id"]], fields["parent_frame_id"] - 1)

    @functools.cache
    def stack(frame_id: int) -> tuple[Frame, ...]:
        frames, seen = [], set()
        while frame_id in parents and frame_id not in seen:
            seen.add(frame_id)
            frame, frame_id = parents[frame_id]
            frames.append(frame)
        return tuple(frames)

    found = {}
    for name, rest in instructions(hlo).items():
        match = _FRAME_ID.search(rest)
        if match:
            found[name] = stack(int(match.group(1)))
    return found


@dataclasses.dataclass(frozen=True)
class Rule:
    """An instruction belongs to ``part`` when a frame of its call stack is in a file whose path contains
    ``file`` and in a function whose qualified name contains ``function`` (an empty pattern matches any)."""

    part: str
    file: str = ""
    function: str = ""

    def matches(self, stack: Iterable[Frame]) -> bool:
        return any(self.file in frame.file and self.function in frame.function for frame in stack)


def parts(hlo: str, rules: Iterable[Rule]) -> dict[str, str]:
    """HLO instruction name -> the part of the program it belongs to: the ``part`` of the first of ``rules`` that
    matches its call stack (:func:`call_stacks`), else ``other``; :data:`NO_STACK` for the instructions XLA made
    without one (its copies and layout changes, casts it inserted, loop counters, parameters)."""
    rules = list(rules)
    stacks = call_stacks(hlo)
    found = {}
    for name in instructions(hlo):
        stack = stacks.get(name)
        found[name] = next((rule.part for rule in rules if rule.matches(stack)), OTHER) if stack else NO_STACK
    return found


@dataclasses.dataclass(frozen=True)
class Event:
    """One traced event of a program's instruction: its ``hlo_op`` and duration."""

    op: str
    nanoseconds: float


def self_times(spans: list[tuple[float, float]]) -> list[float]:
    """Each span's ``end - start`` less the spans nested in it (its children, not their children): the time it
    spent itself. ``spans`` are ``(start, end)`` of one trace line, where events nest or follow each other."""
    order = sorted(range(len(spans)), key=lambda i: (spans[i][0], -spans[i][1]))
    own = [end - start for start, end in spans]
    open_spans: list[int] = []
    for i in order:
        start, end = spans[i]
        while open_spans and spans[open_spans[-1]][1] <= start:
            open_spans.pop()
        if open_spans:
            own[open_spans[-1]] -= end - start
        open_spans.append(i)
    return own


def trace_events(path: pathlib.Path, module: str) -> tuple[list[Event], list[str]]:
    """The events of the ``.xplane.pb`` under ``path`` whose ``hlo_module`` stat names ``module``, with the lines
    they came from: the device planes' stream lines where a ``/device:`` plane exists, else every host line.

    Each event's time is its own (:func:`self_times`): on the CPU a loop's or a call's thunk holds its body's thunks
    on the same line; a GPU stream's kernels do not nest."""
    (xplane,) = path.rglob("*.xplane.pb")
    planes = list(jax.profiler.ProfileData.from_file(str(xplane)).planes)
    devices = [plane for plane in planes if plane.name.startswith("/device:")]
    events, lines = [], set()
    for plane in devices or planes:
        for line in plane.lines:
            if devices and not line.name.startswith("Stream"):
                continue  # derived lines (XLA Ops, XLA Modules) repeat the streams' kernels
            ops, spans = [], []
            for event in line.events:
                stats = dict(event.stats)
                if "hlo_op" in stats and module in str(stats.get("hlo_module", "")):
                    ops.append(str(stats["hlo_op"]))
                    spans.append((float(event.start_ns), float(event.start_ns) + float(event.duration_ns)))
                    lines.add(f"{plane.name} {line.name}")
            events += [Event(op, ns) for op, ns in zip(ops, self_times(spans), strict=True)]
    return events, sorted(lines)


def trace(run: Callable[[Any, int], Any], state: Any, repeats: int, module: str):
    """Runs ``state = run(state, i)`` for ``i`` in ``range(repeats)`` under ``jax.profiler.trace``.

    Args:
      run: one call of a compiled program (already compiled and warmed up).
      state: its first input.
      repeats: traced calls.
      module: the program's HLO module name (:func:`module_name`).

    Returns:
      (the events of ``module``, the trace lines they came from, wall seconds of the calls, the last state).
    """
    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder):
            start = time.perf_counter()
            for i in range(repeats):
                state = run(state, i)
            jax.block_until_ready(state)
            wall = time.perf_counter() - start
        events, lines = trace_events(pathlib.Path(folder), module)
    return events, lines, wall, state


def split(per_op: dict[str, float], mapping: dict[str, str], default: str = NOT_IN_HLO) -> dict[str, float]:
    """Nanoseconds per group: ``per_op``'s sums added up by ``mapping`` (instruction -> group), largest first."""
    groups: dict[str, float] = collections.defaultdict(float)
    for op, ns in per_op.items():
        groups[mapping.get(op, default)] += ns
    return dict(sorted(groups.items(), key=lambda kv: -kv[1]))


def summarize(
    events: list[Event], kinds: dict[str, str], updates: int, top: int, program_parts: dict[str, str] | None = None
) -> dict:
    """Milliseconds per update (``updates`` traced): the whole, per category (``kinds``), and the ``top``
    instructions; with ``program_parts`` (:func:`parts`) also per part and per part and category.

    ``kernels_per_update`` counts the traced events: on a GPU the kernels (and library calls) launched.
    """
    per_op: dict[str, float] = collections.defaultdict(float)
    calls: dict[str, int] = collections.defaultdict(int)
    for event in events:
        per_op[event.op] += event.nanoseconds
        calls[event.op] += 1
    ms = lambda ns: round(ns / 1e6 / updates, 4)
    ranked = sorted(per_op, key=per_op.get, reverse=True)[:top]
    out = {
        "traced_ms_per_update": ms(sum(per_op.values())),
        "kernels_per_update": len(events) / updates,
        "categories": {name: ms(ns) for name, ns in split(per_op, kinds).items()},
        "top": [
            {"op": op, "category": kinds.get(op, NOT_IN_HLO), "ms": ms(per_op[op]), "calls": calls[op] / updates}
            for op in ranked
        ],
    }
    if program_parts is not None:
        out["parts"] = {name: ms(ns) for name, ns in split(per_op, program_parts, OTHER).items()}
        crossed = {op: f"{program_parts.get(op, OTHER)}\t{kinds.get(op, NOT_IN_HLO)}" for op in per_op}
        by_part: dict[str, dict[str, float]] = collections.defaultdict(dict)
        for key, ns in split(per_op, crossed).items():
            part, kind = key.split("\t")
            by_part[part][kind] = ms(ns)
        out["part_categories"] = dict(by_part)
        for entry in out["top"]:
            entry["part"] = program_parts.get(entry["op"], OTHER)
    return out
