"""TriVLAPolicy under Drake: state in the Context only, seeds, re-initialisation, clear port errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource
from pydrake.systems.sensors import ImageRgba8U

from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.station import load_scenario, make_station
from trivla_drake.systems.latency import LatencyModel
from trivla_drake.systems.policy_wiring import add_trivla_policy
from trivla_drake.systems.trivla_policy import PolicyRates, TriVLAPolicy


@pytest.fixture(scope="module")
def tiny_model():
    return TriVLA(make_config("tiny")).eval()


def _closed_loop(model, rates=None, instruction="pick up the red block"):
    scenario = load_scenario()
    builder = DiagramBuilder()
    station = builder.AddNamedSystem("station", make_station(scenario))
    policy = add_trivla_policy(builder, station, model, rates=rates)
    if instruction is None:  # the caller fixes it on the diagram's `instruction` input
        builder.ExportInput(policy.GetInputPort("instruction"), "instruction")
    else:
        source = builder.AddNamedSystem("instruction", ConstantValueSource(AbstractValue.Make(instruction)))
        builder.Connect(source.get_output_port(), policy.GetInputPort("instruction"))
    diagram = builder.Build()
    return diagram, station, policy


def _rollout(simulator, diagram, station, seconds):
    context = simulator.get_mutable_context()
    simulator.AdvanceTo(context.get_time() + seconds)
    return station.GetOutputPort("panda.state").Eval(station.GetMyContextFromRoot(context)).copy()


def test_policy_drives_the_arm_and_publishes_a_chunk(tiny_model):
    diagram, station, policy = _closed_loop(tiny_model)
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    start = station.GetOutputPort("panda.state").Eval(station.GetMyContextFromRoot(context)).copy()
    end = _rollout(simulator, diagram, station, 0.7)
    chunk = policy.GetOutputPort("action_chunk").Eval(policy.GetMyContextFromRoot(context))
    assert chunk.shape == (10, 7) and np.all(np.isfinite(chunk))
    assert np.abs(end[:7] - start[:7]).max() > 1e-3  # an untrained policy still moves the arm


def test_the_policy_reads_the_cameras_as_rendered_at_its_tick_not_the_held_frame(tiny_model):
    """add_trivla_policy wires the station's `.rgb_image_now` ports: Systems 2 and 3 see the scene at the
    instant of the robot state they are paired with (as in the demonstrations), where the held
    `.rgb_image` (10 fps) may be up to 0.1 s old."""
    diagram, station, policy = _closed_loop(tiny_model)
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    simulator.AdvanceTo(10 / 36 + 2e-4)  # just after the second tick; the held frame is from t = 0.2
    station_context, policy_context = station.GetMyContextFromRoot(context), policy.GetMyContextFromRoot(context)
    sensor = station.GetSubsystemByName("wrist_camera_sensor")
    rendered = sensor.color_image_output_port().Eval(sensor.GetMyContextFromRoot(context)).data
    read = policy.GetInputPort("wrist_rgb").Eval(policy_context).data
    held = station.GetOutputPort("wrist_camera.rgb_image").Eval(station_context).data
    np.testing.assert_array_equal(read, rendered)
    assert np.abs(held.astype(int) - rendered.astype(int)).max() > 30  # the hand moved since t = 0.2


def test_a_system1_reading_its_subgoal_offset_gets_the_robot_state():
    """policy.subgoal_offset: System 1 computes the tcp from the robot_state port it already reads."""
    config = make_config("tiny")
    config = dataclasses.replace(config, policy=dataclasses.replace(
        config.policy, tcp_features=True, instruction_grounding=True, subgoal_offset=True))
    model = TriVLA(config).eval()
    seen = []
    sample_actions = model.sample_actions

    def spy(*args, **kwargs):  # what System 1's inference hands the model
        seen.append(np.array(kwargs["state"]))
        return sample_actions(*args, **kwargs)

    model.sample_actions = spy
    diagram, station, policy = _closed_loop(model)
    simulator = Simulator(diagram)
    start = station.GetOutputPort("panda.state").Eval(station.GetMyContextFromRoot(simulator.get_context())).copy()
    _rollout(simulator, diagram, station, 0.3)
    chunk = policy.GetOutputPort("action_chunk").Eval(policy.GetMyContextFromRoot(simulator.get_context()))
    assert chunk.shape == (10, 7) and np.all(np.isfinite(chunk))
    # The first inference read the robot's state at its tick (the arm still at its start: the offset MLP starts at
    # zero, so the chunk alone would not show a missing state).
    assert seen and seen[0].shape == (18,)
    np.testing.assert_allclose(seen[0][:9], start[:9], atol=1e-3)


def test_same_seed_same_rollout_and_contexts_are_independent(tiny_model):
    diagram, station, policy = _closed_loop(tiny_model)
    alone = Simulator(diagram)
    reference = [_rollout(alone, diagram, station, 0.3) for _ in range(2)]

    # Two contexts of the same diagram simulated alternately match the one simulated alone.
    first, second = Simulator(diagram), Simulator(diagram)
    policy.set_seed(second.get_mutable_context(), 123)  # a different seed in the second context
    interleaved = []
    for _ in range(2):
        interleaved.append(_rollout(first, diagram, station, 0.3))
        _rollout(second, diagram, station, 0.3)
    np.testing.assert_array_equal(np.array(interleaved), np.array(reference))
    assert not np.array_equal(_rollout(second, diagram, station, 0.0), reference[-1])


def test_reinitialising_a_context_restarts_the_policy(tiny_model):
    diagram, station, policy = _closed_loop(tiny_model)
    simulator = Simulator(diagram)
    first = _rollout(simulator, diagram, station, 0.6)
    context = simulator.get_mutable_context()
    context.SetTime(0.0)
    diagram.SetDefaultContext(context)
    simulator.Initialize()
    np.testing.assert_array_equal(_rollout(simulator, diagram, station, 0.6), first)


def test_instruction_change_is_taken_at_the_next_system2_update(tiny_model):
    rates = PolicyRates(vision_language_period_s=0.25, dynamics_period_s=0.25, policy_period_s=0.25)
    diagram, station, policy = _closed_loop(tiny_model, rates, instruction=None)
    system2 = policy.systems["vision_language"]
    runs = []
    for new_instruction in ("pick up the red block", "open the drawer"):  # unchanged vs changed
        simulator = Simulator(diagram)
        context = simulator.get_mutable_context()
        diagram.GetInputPort("instruction").FixValue(context, "pick up the red block")
        simulator.AdvanceTo(0.1)
        diagram.GetInputPort("instruction").FixValue(context, new_instruction)
        q_vl = []
        for t in (0.2, 0.3):
            simulator.AdvanceTo(t)
            q_vl.append(system2.GetOutputPort("q_vl").Eval(system2.GetMyContextFromRoot(context)).copy())
        runs.append(q_vl)
    # Before the next System 2 update (0.25 s) the change has no effect; after it, it has.
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    assert not np.array_equal(runs[0][1], runs[1][1])


def test_latency_delays_publication_in_sim_time(tiny_model):
    rates = PolicyRates(latency=LatencyModel("fixed", 0.1))
    diagram, station, policy = _closed_loop(tiny_model, rates)
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    policy_system = policy.systems["policy"]
    pc = policy_system.GetMyContextFromRoot(context)
    # System 2/3 publish at 0.1 s; System 1 first runs at its second tick, 10/36 s (plus its stage
    # offset), and publishes 0.1 s later.
    first_run = 10 / 36 + 2 * rates.stage_offset_s
    simulator.AdvanceTo(first_run + 0.05)
    assert policy_system.GetOutputPort("action_chunk").Eval(pc) is None
    simulator.AdvanceTo(first_run + 0.11)
    assert policy_system.GetOutputPort("action_chunk").Eval(pc) is not None
    assert policy_system.GetOutputPort("action_chunk_stamp").Eval(pc)[0] == pytest.approx(first_run)


def test_unconnected_image_port_fails_at_simulation_start(tiny_model):
    builder = DiagramBuilder()
    policy = builder.AddSystem(TriVLAPolicy(tiny_model))
    for name in ("instruction",):
        builder.ExportInput(policy.GetInputPort(name), name)
    builder.ExportInput(policy.GetInputPort("robot_state"), "robot_state")
    builder.ExportInput(policy.GetInputPort("static_rgb"), "static_rgb")
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    diagram.GetInputPort("instruction").FixValue(context, "lift the red block")
    diagram.GetInputPort("robot_state").FixValue(context, np.zeros(18))
    diagram.GetInputPort("static_rgb").FixValue(context, ImageRgba8U(224, 224))
    with pytest.raises(ValueError, match="wrist_rgb.*(not connected|is it connected)"):
        Simulator(diagram, context).Initialize()


def test_wrong_image_size_fails_at_simulation_start(tiny_model):
    builder = DiagramBuilder()
    policy = builder.AddSystem(TriVLAPolicy(tiny_model))
    for i in range(policy.num_input_ports()):
        builder.ExportInput(policy.get_input_port(i), policy.get_input_port(i).get_name())
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    diagram.GetInputPort("instruction").FixValue(context, "lift the red block")
    diagram.GetInputPort("robot_state").FixValue(context, np.zeros(18))
    diagram.GetInputPort("static_rgb").FixValue(context, ImageRgba8U(224, 224))
    diagram.GetInputPort("wrist_rgb").FixValue(context, ImageRgba8U(640, 480))
    with pytest.raises(ValueError, match="wrist_rgb.*640x480.*224x224"):
        Simulator(diagram, context).Initialize()


def test_replanning_every_k_steps_updates_all_three_systems_at_that_rate_and_keeps_the_covering_chunks(tiny_model):
    rates = PolicyRates.replanning_every(2, ensemble_decay=0.1)
    assert rates.policy_period_s == rates.vision_language_period_s == rates.dynamics_period_s == pytest.approx(2 / 36)
    assert rates.ensemble_decay == 0.1
    diagram, station, policy = _closed_loop(tiny_model, rates)
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.35)
    context = simulator.get_context()
    policy_system, executor = policy.systems["policy"], policy.systems["executor"]
    # The newest chunk was observed at the last multiple of 2/36 s (plus System 1's stage offset).
    offset = 2 * rates.stage_offset_s
    stamp = policy_system.GetOutputPort("action_chunk_stamp").Eval(policy_system.GetMyContextFromRoot(context))[0]
    assert stamp == pytest.approx(12 / 36 + offset)
    # A 10-step chunk observed every 2 steps: the 5 newest chunks all cover the next tick, and all are kept.
    history = executor.GetMyContextFromRoot(context).get_abstract_state(0).get_value()
    np.testing.assert_allclose(history.stamps, np.arange(4, 13, 2) / 36 + offset)


@pytest.mark.parametrize("stage_offset_s", [PolicyRates.stage_offset_s, 0.0])
def test_each_chunk_is_played_from_its_first_action_at_the_instant_of_its_observation(tiny_model, stage_offset_s):
    """Sense, think, act in one instant: the first chunk comes at t = 0 and every tick plays an action.
    With no stage offsets (Drake's simultaneous updates), System 1 would wait a period for System 2/3's
    features and each chunk would reach the executor one tick late."""
    rates = PolicyRates(stage_offset_s=stage_offset_s)
    diagram, station, policy = _closed_loop(tiny_model, rates)
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    policy_system, executor = policy.systems["policy"], policy.systems["executor"]
    simulator.AdvanceTo(15 / 36 + 0.01)
    pc, ec = policy_system.GetMyContextFromRoot(context), executor.GetMyContextFromRoot(context)
    chunk = policy_system.GetOutputPort("action_chunk").Eval(pc)
    stamp = policy_system.GetOutputPort("action_chunk_stamp").Eval(pc)[0]
    played = executor.played_actions(ec)
    last_action = executor.GetOutputPort("action").Eval(ec)
    if stage_offset_s > 0:
        assert stamp == pytest.approx(10 / 36 + 2 * stage_offset_s)
        assert played == 16  # ticks 0, 1/36, ..., 15/36
        np.testing.assert_allclose(last_action, chunk[5], rtol=1e-6)  # row 5 at 5 ticks after the observation
    else:
        assert stamp == pytest.approx(10 / 36)  # the first chunk, a period late
        assert played == 5  # rows 1-5 of that chunk, from tick 11/36
        np.testing.assert_allclose(last_action, chunk[5], rtol=1e-6)


def test_stage_offsets_must_fit_in_a_period(tiny_model):
    with pytest.raises(ValueError, match="stage_offset_s"):
        TriVLAPolicy(tiny_model, PolicyRates(stage_offset_s=0.01))  # 3 x 10 ms > 1/36 s


@pytest.mark.parametrize("bad, field", [
    (dict(policy_period_s=0.0), "policy_period_s"),
    (dict(vision_language_period_s=float("nan")), "vision_language_period_s"),
    (dict(ensemble_decay=float("nan")), "ensemble_decay must be a finite number"),
    (dict(ensemble_decay=-1.0), "ensemble_decay must be a finite number"),
])
def test_bad_rates_name_their_field(tiny_model, bad, field):
    with pytest.raises(ValueError, match=field):
        TriVLAPolicy(tiny_model, PolicyRates(**bad))


@pytest.mark.parametrize("bad", [0, -3, 2.5, True])
def test_replanning_every_needs_a_whole_number_of_steps(bad):
    with pytest.raises(ValueError, match="steps must be an integer >= 1"):
        PolicyRates.replanning_every(bad)


def test_the_chunks_that_can_cover_a_tick():
    from trivla_drake.systems.action_chunk_executor import covering_chunks

    dt = 1 / 36
    assert [covering_chunks(10 * dt, k * dt) for k in range(1, 11)] == [10, 5, 4, 3, 2, 2, 2, 2, 2, 1]
    assert covering_chunks(10 * dt, 0.25) == 2  # a period that is no multiple of the control period


def test_a_latency_of_one_period_skips_no_inference():
    """An inference started at tick t_n with a delay of exactly one period is ready at tick t_(n+1), though
    t_n + period may round a float step above Drake's t_(n+1): every tick starts one (none is 'busy')."""
    from trivla_drake.systems.latency import InferenceSlots
    from trivla_drake.systems.periodic_inference import PeriodicInferenceSystem

    period = 10 / 36

    class Counter(PeriodicInferenceSystem):
        def infer(self, context, seed):
            return np.zeros(1)

    system = Counter(period_s=period, latency=LatencyModel("fixed", period), output_name="value",
                     offset_s=PolicyRates.stage_offset_s)
    simulator = Simulator(system)
    simulator.AdvanceTo(300 * period)
    assert system.slots(simulator.get_context()).count == 300  # ticks at offset + n period, n = 0..299
    rounded = [n for n in range(2000) if n * period + period > (n + 1) * period]
    assert rounded, "no tick of this period rounds up: the check above would not test the tolerance"
    slots = InferenceSlots().start(rounded[0] * period, "x", period)
    assert not slots.busy((rounded[0] + 1) * period) and slots.visible((rounded[0] + 1) * period)[0] == "x"


@pytest.mark.parametrize("use_system2", [True, False])
def test_each_system_has_the_same_seed_from_construction_and_from_set_seed(use_system2):
    """System 1, 2 and 3 get the policy's seed plus a fixed offset (0, 1, 2), whichever systems the model
    keeps, so `set_seed(context, s)` gives what building with `seed=s` gives."""
    from trivla_drake.systems.trivla_policy import SEED_OFFSETS

    config = dataclasses.replace(make_config("tiny"), use_system2=use_system2)
    policy = TriVLAPolicy(TriVLA(config).eval(), seed=7)
    context = policy.CreateDefaultContext()
    built = {k: s.GetMyContextFromRoot(context).get_numeric_parameter(0).GetAtIndex(0)
             for k, s in policy.systems.items() if k != "executor"}
    assert built == {k: 7.0 + SEED_OFFSETS[k] for k in built} and ("vision_language" in built) == use_system2
    policy.set_seed(context, 3)
    reseeded = {k: s.GetMyContextFromRoot(context).get_numeric_parameter(0).GetAtIndex(0)
                for k, s in policy.systems.items() if k != "executor"}
    assert reseeded == {k: 3.0 + SEED_OFFSETS[k] for k in built}
