"""A group's update as one CUDA graph: the update on masks kept on the device, which a captured step
replays, is the update on the host's masks; and it does nothing that a capture forbids (checked here on
any machine, by the operations it dispatches). The capture itself is checked where there is a GPU."""

import contextlib
import warnings

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from layered.learners.graphed import GraphedStep, register_generators
from layered.learners.td3 import TD3Config
from layered.learners.td3_group import TD3Group, Variant
from test_td3_group import fill, flat_state, learners

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine")
MASKS = [np.array(m) for m in ([1, 1, 1], [1, 0, 1], [0, 1, 1], [1, 1, 0], [0, 0, 1], [1, 1, 1])]
"""The seeds that update, update after update: every mix, so that the seeds' counts (and policy delays) part."""


def on_device_masks(group: TD3Group) -> TD3Group:
    """`group` updating as a captured group does, through `GraphedStep`s and its device masks (on a CPU the
    steps run eagerly, so this is the update that a GPU captures, run as it is)."""
    group._graphed = {}
    return group


class Masked(TD3Group):
    """A group on device masks that always replays the variant which puts left-out seeds back."""

    def captured_step(self, variant: Variant):
        return super().captured_step(Variant(variant.with_actor, False, False))


def paired(config: TD3Config) -> tuple[TD3Group, TD3Group]:
    host, device = TD3Group(learners([0, 1, 2], config)), on_device_masks(TD3Group(learners([0, 1, 2], config)))
    for group in (host, device):
        fill(group, [0, 1, 2])
    return host, device


@pytest.mark.parametrize("critic_warmup", [0, 3])
def test_the_update_on_device_masks_is_the_update_on_host_masks(critic_warmup):
    """Seeds left out and seeds whose actor still waits included: left-out seeds are stepped by Adam and put
    back exactly, and a follow by 0 leaves a target as it is. (On the host's masks only the seeds that take
    part are computed, and a product over fewer seeds may sum in another order: equal to float rounding.)"""
    host, device = paired(TD3Config(hidden=(32, 16), batch_size=8, buffer_size=100, critic_warmup=critic_warmup))
    for mask in MASKS:
        a, b = host.update(mask.astype(bool)), device.update(mask.astype(bool))
        assert a is not None and b is not None and a.keys() == b.keys()
        for name in a:
            assert np.array_equal(a[name][1], b[name][1])
            rows = a[name][1]
            assert torch.allclose(a[name][0][rows], b[name][0][rows], rtol=1e-6, atol=1e-7), name
    assert list(host.updates) == list(device.updates) == [4, 4, 5]
    for k in range(3):
        mine, theirs = flat_state(host, k), flat_state(device, k)
        assert mine.keys() == theirs.keys()
        for key in mine:
            assert torch.allclose(mine[key], theirs[key], rtol=1e-6, atol=1e-7), f"seed {k}: {key}"


class Dispatched(TorchDispatchMode):
    """Every operation dispatched inside, with its arguments."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple[str, tuple, dict]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        self.calls.append((str(func.overloadpacket.__name__), args, kwargs))
        return func(*args, **kwargs)


READS_BACK = {"_local_scalar_dense", "item", "is_nonzero", "equal", "nonzero", "masked_select", "unique",
              "_unique2", "argwhere"}
"""Operations that read a value on the host or make a shape from values: a capture cannot hold them."""


VARIANTS = [Variant(False, False, False), Variant(True, False, False), Variant(False, True, False),
            Variant(True, True, True)]


@pytest.mark.parametrize("variant", VARIANTS)
def test_the_captured_update_reads_nothing_back_and_draws_from_its_own_generator(variant):
    group = on_device_masks(TD3Group(learners([0, 1, 2])))
    fill(group, [0, 1, 2])
    group.update()  # gradients and moments exist, as after the eager calls that come before a capture
    group._masks.copy_(torch.tensor([[1.0, 0.0, 1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 1.0]]))
    drawn_from = group.torch_rng.get_state()
    with Dispatched() as seen:
        group.captured_step(variant).step()
    names = {name for name, _, _ in seen.calls}
    assert not names & READS_BACK, names & READS_BACK
    assert "_fused_adam_" in names and ("baddbmm" in names)
    assert ("where" in names) == (not variant.every_critic)  # left-out seeds put back, where there can be any
    draws = [(name, kwargs.get("generator")) for name, _, kwargs in seen.calls
             if name in {"rand", "randn", "normal", "uniform_", "normal_", "randint", "bernoulli"}]
    assert [name for name, _ in draws] == ["rand", "randn"]  # the minibatch's indices, the smoothing noise
    assert all(generator is not None for _, generator in draws)  # not the process's default generator
    assert not torch.equal(group.torch_rng.get_state(), drawn_from)  # but the group's
    boolean_indexing = [name for name, args, _ in seen.calls if name.startswith("index")
                        and any(isinstance(i, torch.Tensor) and i.dtype == torch.bool
                                for a in args if isinstance(a, (list, tuple)) for i in a)]
    assert not boolean_indexing


def test_the_update_of_every_seed_is_the_masked_update_on_a_mask_of_every_seed_bit_for_bit():
    """A step whose masks hold every seed replays a graph without the putting back; its numbers are those of the
    graph with it (nothing put back), and the partial masks in between still take the masked one."""
    config = TD3Config(hidden=(32, 16), batch_size=8, buffer_size=100)
    variants, masked = on_device_masks(TD3Group(learners([0, 1, 2], config))), on_device_masks(
        Masked(learners([0, 1, 2], config)))
    for group in (variants, masked):
        fill(group, [0, 1, 2])
    everyone = np.ones(3, bool)
    for mask in (everyone, everyone, np.array([True, False, True]), everyone, everyone):
        a, b = variants.update(mask), masked.update(mask)
        assert a is not None and b is not None
        for name in a:
            assert torch.equal(a[name][0], b[name][0]), name
    assert variants._graphed is not None and set(variants._graphed) == {  # (after the partial mask the seeds'
        Variant(False, True, False), Variant(True, True, True), Variant(False, False, False),  # policy delays part)
        Variant(True, True, False)}
    for k in range(3):
        mine, theirs = flat_state(variants, k), flat_state(masked, k)
        assert all(torch.equal(mine[key], theirs[key]) for key in mine)


def test_the_update_on_host_masks_computes_only_the_seeds_that_take_part():
    """Where the host knows which seeds update (a layer due in some rows), their networks alone are computed;
    on device masks, every seed is (the actors' products batch the seeds, the critics' both twins of each)."""
    host, device = paired(TD3Config(hidden=(32, 16), batch_size=8, buffer_size=100, policy_delay=1))
    for group, seeds in ((host, 2), (device, 3)):
        group.update()
        with Dispatched() as seen:
            group.update(np.array([True, False, True]))
        products = [args[1].shape[0] for name, args, _ in seen.calls if name == "baddbmm"]
        assert products and set(products) == {seeds, 2 * seeds}


def test_acting_through_a_graph_per_number_of_observations_gives_the_eager_actions():
    """On a CPU the graphs run eagerly: the plumbing (a buffer and a graph per n, the actions read out of it)
    is what is checked here; the capture, on a GPU below."""
    eager, graphed = TD3Group(learners([0, 1, 2])), TD3Group(learners([0, 1, 2]))
    graphed._acting = {}
    rng = np.random.default_rng(2)
    for _ in range(5):
        obs, lanes = rng.normal(size=(3, eager.obs_dim)), rng.normal(size=(3, 4, eager.obs_dim))
        assert np.array_equal(eager.act(obs, explore=False), graphed.act(obs, explore=False))
        assert np.array_equal(eager.greedy(lanes), graphed.greedy(lanes))
    assert set(graphed._acting) == {1, 4} and all(step.calls == 5 for _, step in graphed._acting.values())


def test_a_graphed_step_runs_eagerly_on_a_cpu():
    calls = []
    step = GraphedStep(lambda: calls.append(1) or torch.ones(1), torch.device("cpu"), eager=1)
    for _ in range(3):
        assert torch.equal(step(), torch.ones(1))
    assert len(calls) == 3 and not step.captured


class FakeStream:
    def __init__(self, *args):
        self.waited_for = []

    def wait_stream(self, other):
        self.waited_for.append(other)


class FakeGraph:
    """Stands for a CUDA graph on a CPU: the capture runs the step once (a real one only records it)."""

    def __init__(self):
        self.generators, self.replays, self.stream = [], 0, None

    def register_generator_state(self, generator):
        self.generators.append(generator)

    def replay(self):
        self.replays += 1


@pytest.fixture
def fake_cuda(monkeypatch):
    """torch.cuda's graph and streams stood in for: the graphs and streams made, and the current stream."""
    graphs, streams, current = [], [], FakeStream()

    @contextlib.contextmanager
    def capturing(graph, stream):
        graph.stream = stream
        yield

    monkeypatch.setattr(torch.cuda, "CUDAGraph", lambda: graphs.append(FakeGraph()) or graphs[-1])
    monkeypatch.setattr(torch.cuda, "Stream", lambda device: streams.append(FakeStream()) or streams[-1])
    monkeypatch.setattr(torch.cuda, "current_stream", lambda device: current)
    monkeypatch.setattr(torch.cuda, "stream", lambda stream: contextlib.nullcontext())
    monkeypatch.setattr(torch.cuda, "graph", capturing)
    return graphs, streams, current


def test_a_graphed_step_is_eager_on_the_capture_stream_then_captured_once_then_replayed(fake_cuda):
    """The bookkeeping of the GPU path."""
    graphs, streams, current = fake_cuda
    generator, calls = torch.Generator(), []
    step = GraphedStep(lambda: calls.append(1) or torch.full((2,), float(len(calls))), torch.device("cuda"),
                       [generator], eager=3)
    outputs = [step() for _ in range(6)]
    assert len(calls) == 4 and len(graphs) == 1 and len(streams) == 1  # 3 eager calls and the capture's
    graph = graphs[0]
    assert graph.generators == [generator] and graph.stream is streams[0] and graph.replays == 3
    assert [float(o[0]) for o in outputs] == [1.0, 2.0, 3.0, 4.0, 4.0, 4.0]
    assert all(out is step.outputs for out in outputs[3:])  # the graph's own, no copy launched
    assert not any(out is step.outputs for out in outputs[:3])
    assert streams[0].waited_for == [current] * 4 and current.waited_for == [streams[0]] * 4


class DeprecatedRegistration(FakeGraph):
    """A graph of a torch that registers generators by itself and warns when asked to."""

    def register_generator_state(self, generator):
        warnings.warn("register_generator_state is deprecated and does nothing", FutureWarning, stacklevel=2)


class NoRegistration:
    """A graph of a torch that no longer has the method at all."""

    def __init__(self):
        self.generators = []


@pytest.mark.parametrize("kind", [DeprecatedRegistration, NoRegistration])
def test_a_torch_that_registers_generators_itself_is_not_asked_to_or_quietly(kind):
    graph = kind()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        register_generators(graph, [torch.Generator()])
    assert graph.generators == []


@CUDA
def test_a_captured_group_update_is_the_eager_one_on_the_gpu():
    """Captured after its eager calls, replayed with new masks each time; the same numbers as eager updates
    (the same kernels, launched by the graph), each replay's losses read before the next overwrites them."""
    config = TD3Config(hidden=(64, 64), batch_size=32, buffer_size=200, device="cuda",
                       precision="float32")  # the capture is checked, not the precision
    eager = TD3Group(learners([0, 1, 2], config))
    graphed = TD3Group(learners([0, 1, 2], config.model_copy(update={"compile": "cudagraphs"})))
    for group in (eager, graphed):
        fill(group, [0, 1, 2])
    for mask in MASKS * 2:
        a, b = eager.update(mask.astype(bool)), graphed.update(mask.astype(bool))
        for name in a:
            rows = a[name][1]
            assert torch.allclose(a[name][0][rows], b[name][0][rows], rtol=1e-5, atol=1e-6), name
    assert graphed._graphed is not None and any(step.captured for step in graphed._graphed.values())
    for k in range(3):
        mine, theirs = flat_state(eager, k), flat_state(graphed, k)
        for key in mine:
            assert torch.allclose(mine[key].float(), theirs[key].float(), rtol=1e-4, atol=1e-5), f"seed {k}: {key}"


@CUDA
def test_a_captured_group_acts_as_the_eager_one_on_the_gpu():
    """The actor's kernels launched by one graph give every seed the very actions eager ones give (a resumed
    group acts eagerly for a few steps where the uninterrupted one replays)."""
    config = TD3Config(hidden=(64, 64), device="cuda")
    eager = TD3Group(learners([0, 1, 2], config))
    graphed = TD3Group(learners([0, 1, 2], config.model_copy(update={"compile": "cudagraphs"})))
    rng = np.random.default_rng(0)
    for obs in rng.normal(size=(8, 3, eager.obs_dim)).astype(np.float32):
        assert np.array_equal(eager.act(obs, explore=False), graphed.act(obs, explore=False))
    for lanes in rng.normal(size=(8, 3, 4, eager.obs_dim)).astype(np.float32):  # an evaluation's, side by side
        assert np.array_equal(eager.greedy(lanes), graphed.greedy(lanes))
    assert graphed._acting is not None and set(graphed._acting) == {1, 4}
    assert all(step.captured for _, step in graphed._acting.values())
