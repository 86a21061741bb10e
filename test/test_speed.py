"""Speed work (issue #18 item 5): stage timings, the torch backend's inference copy, the
heap retention, and the benchmark helpers. Figures themselves are not tested (the
machine is shared); what the benchmarks print them from is."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from signal_light_node.boxes import TrackBox
from signal_light_node.model import ModelConfig, build_model
from signal_light_node.model.backends.torch_backend import TorchBackend, inference_copy
from signal_light_node.model.onnx_export import synthetic_tracks
from signal_light_node.runtime.engine import ENGINE_STAGES, EngineConfig, LightStateEngine
from signal_light_node.runtime.memory import retain_freed_memory
from signal_light_node.runtime.stats import StageWindows

TINY = dict(input_size=24, attention_channels=(4, 4, 4), backbone_channels=(6, 8, 8),
            lstm_hidden=(6, 5), head_channels=4, head_grid=2, fc_hidden=16,
            temporal_input=True)


def _tiny_net(seed: int = 0, **overrides):
    torch.manual_seed(seed)
    net = build_model(ModelConfig(**{**TINY, **overrides}))
    # Batch-norm statistics off their defaults, so a fold that ignored them would show.
    with torch.no_grad():
        for module in net.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.running_mean.uniform_(-0.5, 0.5)
                module.running_var.uniform_(0.5, 2.0)
                module.weight.uniform_(0.5, 1.5)
                module.bias.uniform_(-0.2, 0.2)
    return net.eval()


def test_inference_copy_folds_batch_norms_and_leaves_the_model_alone():
    net = _tiny_net()
    before = {k: v.clone() for k, v in net.state_dict().items()}
    folded = inference_copy(net)
    assert folded is not net
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules()) == 6
    # The attention's last conv (C -> 1) is a depthwise conv and a channel sum.
    from signal_light_node.model.inference import ChannelSumConv

    assert isinstance(folded.attention_net.body[-1], ChannelSumConv)
    assert type(net.attention_net.body[-1]) is torch.nn.Conv2d
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())
    frames = synthetic_tracks(24, 3, 4, seed=2)
    ref, fast = TorchBackend(net), TorchBackend(net)
    assert fast.model is net  # the backend still names the model it was given
    sa, sb = ref.initial_state(3), fast.initial_state(3)
    with torch.inference_mode():
        for crops in frames:
            x = torch.from_numpy(crops).permute(0, 3, 1, 2).float() / 255.0
            pa, sa = net.step(x, sa)
            out = fast.step(crops, sb)
            sb = out.state
            for task, probs in pa.items():
                np.testing.assert_allclose(out.probs[task], probs.numpy(), atol=1e-5)


def test_inference_copy_keeps_models_it_cannot_rewrite():
    plain = _tiny_net(norm="group", use_attention=False)
    assert inference_copy(plain) is plain
    group = _tiny_net(norm="group")  # no batch norm, but the attention's last conv
    assert inference_copy(group) is not group
    training = _tiny_net().train()
    assert inference_copy(training) is training
    bare = object()
    assert inference_copy(bare) is bare


def test_retain_freed_memory_is_idempotent():
    first = retain_freed_memory()
    assert isinstance(first, bool) and retain_freed_memory() is first


def test_engine_reports_its_stages_and_they_add_up():
    engine = LightStateEngine(_tiny_net(), EngineConfig())
    image = np.random.default_rng(0).integers(0, 256, (120, 200, 3), dtype=np.uint8)
    boxes = [TrackBox("a", 10, 10, 60, 50), TrackBox("b", 100, 20, 150, 90)]
    for t in range(3):
        frame = engine.process(image, t * 100_000_000, boxes)
        assert tuple(frame.stages_s) == ENGINE_STAGES
        assert all(v >= 0.0 for v in frame.stages_s.values())
        assert sum(frame.stages_s.values()) <= frame.latency_s + 1e-9
        assert frame.stages_s["step"] > 0.0
    empty = engine.process(image, 400_000_000, [])
    assert tuple(empty.stages_s) == ENGINE_STAGES and empty.stages_s["step"] == 0.0
    assert engine.unjudged_frame(0, boxes, 200, 120, "bad").stages_s == {}


def test_stage_windows_give_diagnostics_values():
    windows = StageWindows(("decode", "step"))
    assert dict(windows.values())["stage_step_mean_ms"] == "nan"
    for step in (0.010, 0.020, 0.030):
        windows.add({"decode": 0.002, "step": step, "unknown": 1.0})
    values = dict(windows.values())
    assert values["stage_step_mean_ms"] == "20.0" and values["stage_decode_mean_ms"] == "2.0"
    assert set(values) == {"stage_decode_mean_ms", "stage_decode_p95_ms",
                           "stage_step_mean_ms", "stage_step_p95_ms"}


def test_stage_table_and_isa_lines():
    from signal_light_node.tools import benchmarking as bench

    table = bench.stage_table({"torch": {"decode": [0.002, 0.004], "step": [0.010, 0.030]},
                               "onnxruntime": {"decode": [0.003], "step": [0.012]}},
                              ("decode", "step"))
    lines = table.splitlines()
    assert lines[0].split()[:3] == ["stage", "torch", "mean"]
    frame = lines[-1].split()
    assert frame[0] == "frame" and float(frame[1]) == pytest.approx(23.0)
    assert float(frame[4]) == pytest.approx(15.0)
    text = "\n".join(bench.isa_lines(["torch", "onnxruntime"]))
    assert "CPU capability" in text and "ignores ONEDNN_MAX_CPU_ISA" in text
    assert text.startswith(f"CPU: {bench.cpu_model()}, ") and bench.cpu_model()
    with pytest.raises(Exception, match="unknown backend"):
        bench.require_known(["torch", "tensorrt"])
    assert bench.require_known(["torch", "torch", "onnxruntime"]) == ["torch", "onnxruntime"]


def test_replay_times_every_processed_frame_by_stage(tmp_path):
    from signal_light_node.io import bagio
    from signal_light_node.io.conversions import boxes_to_detections, make_header
    from signal_light_node.io.image_codec import bgr_to_compressed_fields
    from signal_light_node.tools.replay import REPLAY_STAGES, replay_bag

    rng = np.random.default_rng(0)
    bag_path = tmp_path / "bag"
    with bagio.BagWriter(bag_path) as bag:
        bag.add_topic("/camera/image/compressed", "sensor_msgs/msg/CompressedImage")
        bag.add_topic("/tracks", "vision_msgs/msg/Detection2DArray")
        for t in range(4):
            stamp = 1_700_000_000_000_000_000 + t * 100_000_000
            header = make_header(stamp, "camera", bagio.make)
            image = rng.integers(0, 256, (90, 160, 3), dtype=np.uint8)
            fields = bgr_to_compressed_fields(image, "jpeg") if t != 2 else \
                {"format": "jpeg", "data": np.frombuffer(b"not a jpeg", np.uint8)}
            bag.write("/camera/image/compressed", stamp,
                      bagio.make("sensor_msgs/msg/CompressedImage", header=header, **fields))
            bag.write("/tracks", stamp, boxes_to_detections(
                header, [TrackBox("a", 10, 10, 60, 50)], bagio.make))
    summary = replay_bag(bag_path, tmp_path / "out", LightStateEngine(_tiny_net(input_size=24)),
                         progress=False)
    assert summary.images == 4 and summary.bad_images == 1
    assert tuple(summary.stages_s) == REPLAY_STAGES
    assert all(len(v) == len(summary.latencies_s) == 3 for v in summary.stages_s.values())
    for k, latency in enumerate(summary.latencies_s):
        engine = sum(summary.stages_s[s][k] for s in ENGINE_STAGES)
        assert engine <= latency + 1e-9 and summary.stages_s["decode"][k] > 0


def test_chunk_bounds_cover_the_batch_in_order():
    from signal_light_node.model.backends.onnx_backend import MIN_CHUNK_TRACKS, chunk_bounds

    for threads in (1, 2, 3, 4):
        for n in range(0, 70):
            bounds = chunk_bounds(n, threads)
            assert bounds[0][0] == 0 and bounds[-1][1] == n
            assert all(a[1] == b[0] for a, b in zip(bounds, bounds[1:]))
            assert len(bounds) == 1 or min(b - a for a, b in bounds) >= MIN_CHUNK_TRACKS
            assert len(bounds) <= max(1, 2 * threads) and (threads > 1 or len(bounds) == 1)
    assert chunk_bounds(32, 2) == [(0, 8), (8, 16), (16, 24), (24, 32)]


def test_onnxruntime_split_batch_is_bit_identical_to_one_run(tmp_path):
    from signal_light_node.model import save_checkpoint
    from signal_light_node.model.onnx_export import export_onnx
    from signal_light_node.model.backends.registry import create_backend

    net = _tiny_net(seed=4, input_size=32)  # 32 / 8 = 4: head_grid 2 divides it
    weights = save_checkpoint(tmp_path / "tiny.pt", net, net.config)
    path = str(export_onnx(tmp_path / "tiny.onnx", weights).path)
    one, split = create_backend("onnxruntime", path, threads=1), \
        create_backend("onnxruntime", path, threads=3)
    assert (one.threads, split.threads) == (1, 3)
    frames = synthetic_tracks(32, 13, 4, seed=5)
    rows_one, rows_split = one.new_rows(13), split.new_rows(13)
    index = np.arange(13)
    for crops in frames:
        a = one.step(crops, one.gather_rows(rows_one, index), attention=True)
        b = split.step(crops, split.gather_rows(rows_split, index), attention=True)
        for task in a.probs:
            np.testing.assert_array_equal(a.probs[task], b.probs[task])
        np.testing.assert_array_equal(a.attention, b.attention)
        one.store_rows(rows_one, index, a.state)
        split.store_rows(rows_split, index, b.state)
    np.testing.assert_array_equal(rows_one, rows_split)


def test_backend_auto_picks_by_file_and_device(monkeypatch):
    from signal_light_node.model.backends import registry as backend_module
    from signal_light_node.model.backends.registry import resolve_backend

    assert resolve_backend("torch") == "torch" and resolve_backend("onnxruntime") == "onnxruntime"
    assert resolve_backend("auto", "/m/best.onnx") == "onnxruntime"
    assert resolve_backend("auto", "/m/BEST.ONNX", "cuda") == "onnxruntime"
    assert resolve_backend("auto", "/m/best.pt") == "torch"
    assert resolve_backend("auto", None, "cpu") == "onnxruntime"
    assert resolve_backend("auto", None, "cuda:1") == "torch"
    monkeypatch.setattr(backend_module.importlib.util, "find_spec", lambda name: None)
    assert resolve_backend("auto", None, "cpu") == "torch"  # onnxruntime not installed


def test_engine_from_checkpoint_with_backend_auto(tmp_path):
    from signal_light_node.model import save_checkpoint
    from signal_light_node.runtime.engine import engine_from_checkpoint

    net = _tiny_net()
    path = save_checkpoint(tmp_path / "tiny.pt", net, net.config)
    assert engine_from_checkpoint(path, backend="auto").backend.name == "torch"
    from signal_light_node.model import onnx_format as fmt

    if fmt.DEFAULT_ONNX.is_file():
        assert engine_from_checkpoint(backend="auto").backend.name == "onnxruntime"


@pytest.mark.parametrize("kwargs", [dict(padding=1), dict(padding=2, dilation=2),
                                    dict(padding=0, stride=2), dict(padding=1, bias=False)])
def test_channel_sum_conv_is_the_single_output_conv(kwargs):
    from signal_light_node.model.inference import ChannelSumConv

    torch.manual_seed(1)
    conv = torch.nn.Conv2d(8, 1, 3, **kwargs).eval()
    x = torch.randn(3, 8, 17, 17)
    with torch.no_grad():
        np.testing.assert_allclose(ChannelSumConv(conv)(x).numpy(), conv(x).numpy(), atol=1e-5)


def test_node_stages_wrap_the_engine_stages():
    pytest.importorskip("rclpy")
    from signal_light_node.ros.detector_node import NODE_STAGES

    assert NODE_STAGES[:2] == ("queue", "decode") and NODE_STAGES[-2:] == ("outputs", "publish")
    assert NODE_STAGES[2:-2] == ENGINE_STAGES
