"""``benchmarks/kernel_profile.py`` (categories, call stacks and parts, matmul FLOPs, self times, per-update sums)
and ``benchmarks/sac_profile.py`` (a traced CPU run of the SAC update and of a round, bad input)."""

from __future__ import annotations

import collections
import inspect
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest


@pytest.fixture
def kp(benchmark_script):
    return benchmark_script("kernel_profile")


@pytest.fixture
def sp(benchmark_script):
    return benchmark_script("sac_profile")


# A GPU-compiled SAC update as XLA prints it, cut down: library GEMMs, a Triton GEMM, elementwise and reduction
# fusions, a copy; the call-stack tables after the computations (jaxlib 0.10.2's numbering).
HLO = """
HloModule jit_many, entry_computation_layout={()->()}

%fused_add (p: f32[1024,1024]) -> f32[1024,1024] {
  %p = f32[1024,1024]{1,0} parameter(0)
  ROOT %add.1 = f32[1024,1024]{1,0} add(f32[1024,1024]{1,0} %p, f32[1024,1024]{1,0} %p)
}

ENTRY %main () -> () {
  %x = bf16[1024,30]{1,0} parameter(0)
  %w = bf16[30,1024]{1,0} parameter(1)
  %custom-call.7 = (bf16[1024,1024]{1,0}, s8[4194304]{0}) custom-call(%x, %w), custom_call_target="__cublas$lt$matmul", backend_config={"gemm_backend_config":{"dot_dimension_numbers":{"lhs_contracting_dimensions":["1"],"rhs_contracting_dimensions":["0"],"lhs_batch_dimensions":[],"rhs_batch_dimensions":[]}}}, metadata={op_name="jit(many)/jvp(DoubleCritic)/Dense_0/dot_general" stack_frame_id=4}
  %gemm_fusion.4 = bf16[8] fusion(%x), kind=kCustom, calls=%fused_add, backend_config={"fusion_backend_config":{"kind":"__triton_gemm"}}, metadata={op_name="jit(many)/dot_general" stack_frame_id=3}
  %loop_add_fusion = f32[1024,1024]{1,0} fusion(%x), kind=kLoop, calls=%fused_add, metadata={op_name="jit(many)/add" stack_frame_id=6}
  %input_reduce_fusion.2 = f32[32]{0} fusion(%x), kind=kInput, calls=%fused_add, metadata={op_name="jit(many)/add" stack_frame_id=7}
  %copy.5 = bf16[30,1024]{0,1} copy(bf16[30,1024]{1,0} %w)
  %dot.3 = f32[5,7,3]{2,1,0} dot(bf16[5,7,11]{2,1,0} %a, bf16[5,11,3]{2,1,0} %b), lhs_batch_dims={0}, lhs_contracting_dims={2}, rhs_batch_dims={0}, rhs_contracting_dims={1}
  ROOT %tuple.1 = () tuple()
}

FileNames
1 "/src/rebel_jax/agents/sac.py"
2 "/site-packages/optax/_src/update.py"
3 "/site-packages/optax/_src/transform.py"

FunctionNames
1 "SAC.update"
2 "SAC._critic_step"
3 "make_critic_loss.<locals>.loss"
4 "polyak"
5 "incremental_update"
6 "scale_by_adam.<locals>.update_fn"

FileLocations
1 {file_name_id=1 function_name_id=1 line=284 end_line=284 column=1 end_column=2}
2 {file_name_id=1 function_name_id=2 line=255 end_line=255 column=1 end_column=2}
3 {file_name_id=1 function_name_id=3 line=112 end_line=112 column=1 end_column=2}
4 {file_name_id=1 function_name_id=4 line=177 end_line=177 column=1 end_column=2}
5 {file_name_id=2 function_name_id=5 line=71 end_line=71 column=1 end_column=2}
6 {file_name_id=3 function_name_id=6 line=299 end_line=299 column=1 end_column=2}

StackFrames
1 {file_location_id=1 parent_frame_id=1}
2 {file_location_id=2 parent_frame_id=2}
3 {file_location_id=3 parent_frame_id=3}
4 {file_location_id=3 parent_frame_id=3}
5 {file_location_id=4 parent_frame_id=2}
6 {file_location_id=5 parent_frame_id=6}
7 {file_location_id=6 parent_frame_id=3}
"""  # noqa: E501 (XLA's lines)


def test_categories_of_a_gpu_update(kp):
    kinds = kp.categories(HLO)
    assert kinds["custom-call.7"] == "matrix product"
    assert kinds["gemm_fusion.4"] == "matrix product"
    assert kinds["loop_add_fusion"] == "fusion kLoop"
    assert kinds["input_reduce_fusion.2"] == "fusion kInput"
    assert kinds["copy.5"] == "copy"
    assert kinds["dot.3"] == "matrix product"
    assert kinds["add.1"] == "add" and kinds["p"] == "parameter" and kinds["tuple.1"] == "tuple"
    assert kp.module_name(HLO) == "jit_many"


def test_call_stacks_follow_the_parent_frames(kp):
    stacks = kp.call_stacks(HLO)
    functions = lambda name: [frame.function for frame in stacks[name]]
    assert functions("gemm_fusion.4") == ["make_critic_loss.<locals>.loss", "SAC._critic_step", "SAC.update"]
    assert [frame.line for frame in stacks["gemm_fusion.4"]] == [112, 255, 284]
    assert functions("loop_add_fusion") == ["incremental_update", "polyak", "SAC.update"]
    assert functions("input_reduce_fusion.2") == ["scale_by_adam.<locals>.update_fn", "SAC._critic_step", "SAC.update"]
    assert "copy.5" not in stacks


def test_parts_take_the_first_rule_that_matches_the_stack(kp, sp):
    found = kp.parts(HLO, sp.UPDATE_PARTS)
    assert found["loop_add_fusion"] == "target update (Polyak)"  # optax's incremental_update, called by polyak
    assert found["input_reduce_fusion.2"] == "optimiser (Adam)"
    assert found["gemm_fusion.4"] == found["custom-call.7"] == "critic loss"
    assert found["copy.5"] == found["tuple.1"] == kp.NO_STACK
    assert kp.parts(HLO, [])["gemm_fusion.4"] == kp.OTHER


def test_call_stacks_of_a_compiled_program_name_its_python_functions(kp):
    def inner(x):
        return jnp.sin(x) * 3.0

    def outer(x):
        return inner(x) + 1.0

    text = jax.jit(outer).lower(jnp.ones(4)).compile().as_text()
    stacks = kp.call_stacks(text)
    sine = [name for name, rest in kp.instructions(text).items() if " sine(" in rest]
    assert sine
    lines, start = inspect.getsourcelines(inner)
    inner_line = start + next(i for i, line in enumerate(lines) if "jnp.sin" in line)
    for name in sine:
        frames = stacks[name]
        assert (frames[0].function.split(".")[-1], frames[0].line) == ("inner", inner_line)
        assert frames[1].function.split(".")[-1] == "outer" and frames[0].file == __file__


def test_dot_flops_of_a_gpu_text_count_library_calls_and_batched_dots(kp):
    library = 2 * 1024 * 1024 * 30  # (1024 x 30) @ (30 x 1024)
    batched = 2 * 5 * 7 * 3 * 11  # 5 batches of (7 x 11) @ (11 x 3)
    assert kp.dot_flops(HLO) == library + batched


def test_dot_flops_of_a_compiled_mlp_gradient_equal_a_hand_count(kp):
    b, i, h, o = 5, 7, 11, 3

    def loss(params, x, y):
        w1, w2 = params
        return jnp.sum((jax.nn.relu(x @ w1) @ w2 - y) ** 2)

    rng = np.random.default_rng(0)
    args = [(jnp.asarray(rng.normal(size=(i, h))), jnp.asarray(rng.normal(size=(h, o))))]
    args += [jnp.asarray(rng.normal(size=(b, i))), jnp.asarray(rng.normal(size=(b, o)))]
    text = jax.jit(jax.grad(loss)).lower(*args).compile().as_text()
    forward = 2 * b * i * h + 2 * b * h * o
    backward = 2 * h * b * o + 2 * b * o * h + 2 * i * b * h  # dW2, the hidden layer's gradient, dW1 (no dx)
    assert kp.dot_flops(text) == forward + backward


def test_self_times_subtract_the_children_only(kp):
    rng = np.random.default_rng(1)
    spans = []
    for start in range(0, 1000, 100):  # a loop thunk, its body's thunks, one nested deeper
        spans.append((start, start + 90))
        spans.append((start + 10, start + 40))
        spans.append((start + 15, start + 20))
        spans.append((start + 50, start + 80))
    order = rng.permutation(len(spans))
    shuffled = [spans[k] for k in order]
    own = kp.self_times(shuffled)

    def reference(span):  # its duration less the spans inside it that no other span inside it holds
        inside = [s for s in spans if s != span and span[0] <= s[0] and s[1] <= span[1]]
        direct = [s for s in inside if not any(t != s and t[0] <= s[0] and s[1] <= t[1] for t in inside)]
        return span[1] - span[0] - sum(e - s for s, e in direct)

    assert own == [reference(span) for span in shuffled]


def test_summarize_splits_the_total_by_category_by_part_and_both(kp):
    rng = np.random.default_rng(0)
    ops = [f"op.{i}" for i in range(9)]
    kinds = {op: ["dot", "fusion", "copy"][i % 3] for i, op in enumerate(ops[:8])}  # op.8 is not in the HLO
    program_parts = {op: ["critic", "adam"][i % 2] for i, op in enumerate(ops[:7])}  # op.7, op.8: other
    events = [kp.Event(str(rng.choice(ops)), float(rng.integers(1, 10_000))) for _ in range(300)]
    updates = 3
    out = kp.summarize(events, kinds, updates, top=4, program_parts=program_parts)

    per_part = collections.defaultdict(float)
    per_both = collections.defaultdict(float)
    for event in events:
        part = program_parts.get(event.op, kp.OTHER)
        per_part[part] += event.nanoseconds / 1e6 / updates
        per_both[part, kinds.get(event.op, kp.NOT_IN_HLO)] += event.nanoseconds / 1e6 / updates
    assert out["parts"] == pytest.approx(dict(per_part), abs=1e-4)
    both = {(part, kind): ms for part, kinds_ms in out["part_categories"].items() for kind, ms in kinds_ms.items()}
    assert both == pytest.approx(dict(per_both), abs=1e-4)
    assert sum(out["parts"].values()) == pytest.approx(out["traced_ms_per_update"], abs=1e-3)
    assert out["kernels_per_update"] == len(events) / updates
    assert all(entry["part"] == program_parts.get(entry["op"], kp.OTHER) for entry in out["top"])


def test_a_traced_cpu_run_of_the_update_splits_it_into_its_parts(sp, tmp_path):
    out = tmp_path / "profile.json"
    sp.main(["--hidden", "16", "--depth", "1", "--batch-size", "8", "--columns", "2", "--repeats", "1",
             "--updates-per-call", "2", "--peak-tflops", "1", "--out", str(out)])  # fmt: skip
    (row,) = json.loads(out.read_text())["rows"]
    assert row["device"] == "cpu" and row["part"] == "update" and row["columns"] == 2 and row["updates"] == 2
    assert row["traced_ms_per_update"] > 0 and row["wall_ms_per_update"] > 0
    assert "not in the HLO" not in row["categories"]
    for split in ("categories", "parts"):
        assert sum(row[split].values()) == pytest.approx(row["traced_ms_per_update"], abs=1e-3)
    assert {"critic loss", "actor loss", "optimiser (Adam)", "target update (Polyak)"} <= set(row["parts"])
    # The analytic count also counts the first layers' input gradients, which the compiled update leaves out.
    assert 0.8 * row["analytic_flops_per_update"] < row["matmul_flops_per_update"] <= row["analytic_flops_per_update"]
    expected = row["matmul_flops_per_update"] / (row["wall_ms_per_update"] / 1e3) / 1e12
    assert row["matmul_tflops"] == pytest.approx(expected, rel=1e-2, abs=1e-3)
    assert row["compiled_launches_per_update"] > 0 and row["kernels_per_update"] > 0


# make test-heavy (10 s, a traced round): the trace reading and categories are tested on the update above.
@pytest.mark.heavy
def test_a_traced_cpu_round_splits_it_into_physics_updates_and_the_rest(sp, tmp_path):
    out = tmp_path / "round.json"
    sp.main(["--part", "round", "--preset", "tiny", "--task", "probe_point", "--algo", "sac", "--columns", "2",
             "--steps-per-round", "400", "--round-index", "1", "--repeats", "1", "--out", str(out)])  # fmt: skip
    (row,) = json.loads(out.read_text())["rows"]
    assert row["part"] == "round" and row["vector_steps"] == 100 and row["updates_per_vector_step"] == 1
    for split in ("categories", "parts"):
        assert sum(row[split].values()) == pytest.approx(row["traced_ms_per_round"], abs=1e-2)
    assert {"physics", "SAC updates", "acting", "replay"} <= set(row["parts"])


@pytest.mark.heavy
def test_a_traced_cpu_pebble_round_with_a_session_shows_the_reward_parts(sp, tmp_path):
    out = tmp_path / "round.json"
    sp.main(["--part", "round", "--preset", "tiny", "--task", "probe_point", "--columns", "2", "--steps-per-round",
             "400", "--round-index", "5", "--repeats", "1", "--out", str(out)])  # fmt: skip
    (row,) = json.loads(out.read_text())["rows"]
    assert row["algo"] == "pebble"
    assert sum(row["parts"].values()) == pytest.approx(row["traced_ms_per_round"], abs=1e-2)
    assert {"physics", "SAC updates", "feedback session", "learned reward"} <= set(row["parts"])


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--repeats", "0"], "--repeats must be at least 1"),
        (["--columns", "5", "0"], "--columns must be at least 1"),
        (["--peak-tflops", "-1"], "--peak-tflops must be positive"),
        (["--part", "round", "--preset", "tiny", "--round-index", "4"], "not a round of this run"),
        (["--part", "round", "--algo", "nope"], "algo='nope' is invalid"),
    ],
)
def test_bad_input_is_one_line_and_status_2(sp, capsys, argv, message):
    with pytest.raises(SystemExit) as exit_info:
        sp.main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1
