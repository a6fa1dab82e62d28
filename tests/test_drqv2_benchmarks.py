"""``benchmarks/drqv2_profile.py`` (the HLO categories, the per-update sums, a traced run on the CPU) and
``benchmarks/shift_bench.py`` (the select-based shift against ``drqv2.shift_images``, a run on the CPU)."""

from __future__ import annotations

import collections
import json

import numpy as np
import pytest


@pytest.fixture
def profile(benchmark_script):
    return benchmark_script("drqv2_profile")


@pytest.fixture
def shift_bench(benchmark_script):
    return benchmark_script("shift_bench")


HLO = """
HloModule jit_many, entry_computation_layout={()->()}

%fused_computation (p: bf16[512,41,41,32]) -> bf16[512,41,41,32] {
  %p = bf16[512,41,41,32]{3,2,1,0} parameter(0)
  ROOT %tanh.1 = bf16[512,41,41,32]{3,2,1,0} tanh(bf16[512,41,41,32]{3,2,1,0} %p)
}

ENTRY %main () -> () {
  %cudnn-conv.3 = (bf16[512,41,41,32]{3,2,1,0}, u8[0]{0}) custom-call(%a, %k), custom_call_target="__cudnn$convForward"
  %cudnn-conv-bw-input.1 = (bf16[8], u8[0]) custom-call(%g, %k), custom_call_target="__cudnn$convBackwardInput"
  %cudnn-conv-bw-filter.2 = (bf16[8], u8[0]) custom-call(%g, %a), custom_call_target="__cudnn$convBackwardFilter"
  %cudnn-conv-bias-act = (bf16[8], u8[0]) custom-call(%a, %k), custom_call_target="__cudnn$convBiasActivationForward"
  %custom-call.7 = (f32[512,1024]{1,0}, s8[4194304]{0}) custom-call(%x, %w), custom_call_target="__cublas$lt$matmul"
  %gemm_fusion.4 = bf16[8] fusion(%x), kind=kCustom, backend_config={"fusion_backend_config":{"kind":"__triton_gemm"}}
  %loop_tanh_fusion = bf16[512,41,41,32]{3,2,1,0} fusion(%cudnn-conv.3), kind=kLoop, calls=%fused_computation
  %input_reduce_fusion.2 = f32[32]{0} fusion(%g), kind=kInput, calls=%fused_reduce
  %copy.5 = bf16[512,84,84,9]{2,1,3,0} copy(bf16[512,84,84,9]{3,2,1,0} %a)
  %conv_general_dilated.86 = f32[8,7,7,32]{3,2,1,0} convolution(%a, %k), dim_labels=b01f_01io->b01f
  %dot.3 = f32[8,50]{1,0} dot(%x, %w), lhs_contracting_dims={1}, rhs_contracting_dims={0}
  %custom-call.9 = f32[8]{0} custom-call(%x), custom_call_target="SomethingElse"
  ROOT %tuple.1 = () tuple()
}
"""


def test_categories_name_each_instruction_by_what_it_computes(profile):
    kinds = profile.categories(HLO)
    assert kinds["tanh.1"] == "tanh"
    assert kinds["p"] == "parameter"
    assert kinds["cudnn-conv.3"] == "convolution forward"
    assert kinds["cudnn-conv-bias-act"] == "convolution forward"
    assert kinds["cudnn-conv-bw-input.1"] == "convolution input gradient"
    assert kinds["cudnn-conv-bw-filter.2"] == "convolution kernel gradient"
    assert kinds["custom-call.7"] == "matrix product"
    assert kinds["gemm_fusion.4"] == "matrix product"
    assert kinds["loop_tanh_fusion"] == "fusion kLoop"
    assert kinds["input_reduce_fusion.2"] == "fusion kInput"
    assert kinds["copy.5"] == "copy"
    assert kinds["conv_general_dilated.86"] == "convolution (XLA)"
    assert kinds["dot.3"] == "matrix product"
    assert kinds["custom-call.9"] == "custom-call SomethingElse"
    assert kinds["tuple.1"] == "tuple"


def test_summarize_sums_each_instruction_and_category_per_update_as_a_loop_does(profile):
    rng = np.random.default_rng(0)
    ops = [f"op.{i}" for i in range(7)]
    kinds = {op: ["conv", "fusion", "copy"][i % 3] for i, op in enumerate(ops[:6])}  # op.6 is not in the HLO
    events = [profile.Event(str(rng.choice(ops)), float(rng.integers(1, 10_000))) for _ in range(200)]
    updates = 4
    out = profile.summarize(events, kinds, updates, top=3)

    per_op, calls = collections.defaultdict(float), collections.defaultdict(int)
    for event in events:
        per_op[event.op] += event.nanoseconds
        calls[event.op] += 1
    per_category = collections.defaultdict(float)
    for op, ns in per_op.items():
        per_category[kinds.get(op, "not in the HLO")] += ns
    assert out["traced_ms_per_update"] == pytest.approx(sum(per_op.values()) / 1e6 / updates, abs=1e-4)
    assert out["categories"] == pytest.approx({k: v / 1e6 / updates for k, v in per_category.items()}, abs=1e-4)
    assert list(out["categories"].values()) == sorted(out["categories"].values(), reverse=True)
    ranked = sorted(per_op, key=per_op.get, reverse=True)[:3]
    assert [entry["op"] for entry in out["top"]] == ranked
    for entry in out["top"]:
        assert entry["ms"] == pytest.approx(per_op[entry["op"]] / 1e6 / updates, abs=1e-4)
        assert entry["calls"] == calls[entry["op"]] / updates
        assert entry["category"] == kinds.get(entry["op"], "not in the HLO")


# make test-heavy (10 s, a traced pixel update): the categories and the sums are tested above on HLO text.
@pytest.mark.heavy
def test_a_traced_cpu_run_finds_every_instruction_in_the_compiled_program(profile, tmp_path):
    out = tmp_path / "profile.json"
    profile.main(["--size", "16", "--batch-size", "4", "--seeds", "2", "--repeats", "1", "--updates-per-call", "2",
                  "--out", str(out)])  # fmt: skip
    (row,) = json.loads(out.read_text())["rows"]
    assert row["device"] == "cpu" and row["updates"] == 2 and row["seed_loop"] is True
    assert row["traced_ms_per_update"] > 0 and row["wall_ms_per_update"] > 0
    assert "not in the HLO" not in row["categories"]
    assert sum(row["categories"].values()) == pytest.approx(row["traced_ms_per_update"], abs=1e-3)
    assert "convolution (XLA)" in row["categories"]  # the encoder's convolutions ran and were traced


def test_bad_counts_are_refused(profile):
    with pytest.raises(SystemExit, match="at least 1"):
        profile.main(["--repeats", "0"])


@pytest.mark.parametrize("pad", [1, 4])
def test_shift_by_selects_takes_the_same_window_as_shift_images_at_every_shift(shift_bench, pad):
    import jax.numpy as jnp

    from rebel_jax.agents.drqv2 import shift_images

    rng = np.random.default_rng(pad)
    shifts = np.array([(sx, sy) for sx in range(2 * pad + 1) for sy in range(2 * pad + 1)])
    obs = jnp.asarray(rng.integers(0, 256, (len(shifts), 10, 12, 9), dtype=np.uint8))
    ours = np.asarray(shift_bench.shift_by_selects(obs, jnp.asarray(shifts), pad))
    assert ours.dtype == np.uint8
    np.testing.assert_array_equal(ours, np.asarray(shift_images(obs, jnp.asarray(shifts), pad)))


def test_a_shift_bench_cpu_run_writes_a_row_per_way_and_output(shift_bench, tmp_path):
    out = tmp_path / "shift.json"
    shift_bench.main(["--batch-size", "4", "--size", "12", "--per-call", "2", "--repeats", "1", "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert sorted((row["way"], row["output"]) for row in rows) == sorted(
        (way, output) for way in shift_bench.WAYS for output in ("u8", "scaled")
    )
    assert all(row["ms"] > 0 and row["batch_size"] == 4 for row in rows)
