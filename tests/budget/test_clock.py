"""The two clocks: real-time replay (wall clock, bounded drop-oldest queue) and the deterministic budget."""

import time
from types import SimpleNamespace

import numpy as np
import pytest

import eligsir_o3d as eo3d
from eligsir_o3d.budget import BudgetClock, ClockConfig, CostModel, RealtimeClock, get_clock
from eligsir_o3d.core.frame import Frame, FrameError


class StubMapper:
    """The part of the Reconstructor a clock talks to; integrate/updates cost a fixed wall time."""

    def __init__(self, frame_s=0.0, update_s=0.0, bad=()):
        self.frame_s, self.update_s, self.bad = frame_s, update_s, set(bad)
        self.backlog = 0
        self.backlogs = []
        self.integrated = []
        self.stats = SimpleNamespace(updates=0, supervised_pixels=0)
        self.gmap = [0] * 100
        self.attached = []  # (period_s, cost model) of every load report that carried a period
        self.t0 = time.perf_counter()

    def clock_now(self):
        return time.perf_counter()

    def set_load(self, backlog, period_s=None, cost=None):
        self.backlog = backlog
        if period_s is not None:
            self.attached.append((period_s, cost))

    def integrate(self, frame, pose=None, timestamp=None, *, updates=None, deadline=None):
        if frame.index in self.bad:
            raise FrameError(f"frame {frame.index}: depth has no valid measurement")
        self.backlogs.append(self.backlog)
        self.integrated.append(frame.index)
        time.sleep(self.frame_s)
        self.optimize(updates, deadline)

    def optimize(self, updates=None, deadline=None, scale=None):
        done = 0
        while (updates is None or done < updates) and (deadline is None or self.clock_now() < deadline):
            if self.update_s:
                time.sleep(self.update_s)
            self.stats.updates += 1
            self.stats.supervised_pixels += 1000
            done += 1
            if updates is None and deadline is None:
                break
        return done


def _frames(n, fps=100.0):
    cam = eo3d.Camera(8, 6, 5.0, 5.0, 3.5, 2.5)
    color = np.zeros((6, 8, 3), np.float32)
    depth = np.ones((6, 8), np.float32)
    return [Frame.from_arrays(color, depth, cam, np.eye(4), timestamp=i / fps, index=i) for i in range(n)]


def test_realtime_replay_drops_and_counts_frames_when_the_mapper_is_too_slow():
    frames = _frames(30, fps=100.0)  # a frame every 10 ms, the mapper needs 35 ms per frame
    rec = StubMapper(frame_s=0.035)
    t0 = time.perf_counter()
    report = RealtimeClock(queue_size=2).run(rec, frames)
    wall = time.perf_counter() - t0
    assert report.released == 30
    assert report.dropped > 10 and report.integrated + report.dropped == 30
    assert sorted(rec.integrated + report.dropped_indices) == list(range(30))
    assert report.max_backlog <= 2 and max(rec.backlogs) >= 1  # the fidelity controller saw the backlog
    assert rec.integrated[-1] == 29  # drop-oldest: the newest frame is always mapped
    assert rec.backlog == 0
    assert wall < report.stream_s + 3 * 0.035 + 0.25  # bounded lag: it finishes right after the stream
    assert rec.attached and rec.attached[-1][0] == pytest.approx(0.01) and rec.attached[-1][1] is None


def test_realtime_replay_keeps_up_and_optimises_between_frames():
    frames = _frames(10, fps=25.0)
    rec = StubMapper(frame_s=0.002, update_s=0.002)
    report = RealtimeClock(speed=2.0, queue_size=10).run(rec, frames)  # every 20 ms
    assert report.dropped == 0 and report.integrated == 10
    assert rec.stats.updates >= 10  # the time between releases went to optimisation (not just one per frame)
    assert report.stream_s == pytest.approx(9 / 25.0 / 2.0)
    assert rec.attached[-1][0] == pytest.approx(0.02)


def test_budget_clock_replays_against_modelled_time_deterministically():
    def run():
        rec = StubMapper()
        cost = CostModel(update_s=0.025, gaussian_s=0.0, pixel_s=0.0, pixel_gaussian_s=0.0, frame_s=0.004)
        report = BudgetClock(cost=cost, queue_size=1).run(rec, _frames(20, fps=100.0))
        return report, rec

    (r1, m1), (r2, m2) = run(), run()
    assert (r1.dropped, r1.dropped_indices, m1.stats.updates, m1.integrated) == \
           (r2.dropped, r2.dropped_indices, m2.stats.updates, m2.integrated)
    # a 4 ms frame + a 25 ms update (the first update overruns the deadline) per 10 ms period: most are dropped
    assert r1.dropped > 5 and r1.integrated + r1.dropped == 20
    assert r1.elapsed_s >= r1.stream_s
    period, cost = m1.attached[-1]
    assert period == pytest.approx(0.01) and cost.update(1000, 100) == pytest.approx(0.025)


def test_budget_clock_with_fixed_updates_integrates_every_frame():
    rec = StubMapper()
    report = BudgetClock(3).run(rec, _frames(5))
    assert report.integrated == 5 and report.dropped == 0 and rec.stats.updates == 15


@pytest.mark.parametrize("clock", [RealtimeClock(speed=10.0, queue_size=10), BudgetClock(2), BudgetClock()])
def test_bad_frames_are_skipped_or_stop_the_run(clock):
    rec = StubMapper(bad={3})
    report = clock.run(rec, _frames(6))
    assert report.skipped_bad == ["frame 3: depth has no valid measurement"]
    assert 3 not in rec.integrated and report.integrated == 5
    clock.on_bad_frame = "stop"
    with pytest.raises(FrameError, match="frame 3"):
        clock.run(StubMapper(bad={3}), _frames(6))


def test_a_failing_reader_is_skipped():
    frames = _frames(4)

    class Reader:
        def __init__(self):
            self.i = 0

        def __iter__(self):
            return self

        def __next__(self):
            self.i += 1
            if self.i > 4:
                raise StopIteration
            if self.i == 2:
                raise FrameError("frame 1: colour must be HxWx3")
            return frames[self.i - 1]

    report = BudgetClock(1).run(StubMapper(), Reader())
    assert report.integrated == 3 and report.skipped_bad == ["frame 1: colour must be HxWx3"]


def test_get_clock_from_config():
    cfg = eo3d.Config()
    assert isinstance(get_clock(cfg), BudgetClock) and get_clock(cfg).updates_per_frame is None
    cfg.clock = ClockConfig(mode="updates")
    assert get_clock(cfg).updates_per_frame == cfg.clock.updates_per_frame
    cfg.clock = ClockConfig(mode="realtime", speed=0.5, queue_size=3)
    clock = get_clock(cfg)
    assert isinstance(clock, RealtimeClock) and clock.speed == 0.5 and clock.queue_size == 3
    with pytest.raises(ValueError, match="on_bad_frame"):
        RealtimeClock(on_bad_frame="ignore")


def test_realtime_replay_with_the_reconstructor():
    from eligsir_o3d.datasets import open_sequence

    seq = open_sequence("synthetic", n_frames=12, width=64, height=48)
    cfg = eo3d.Config(renderer="torch")
    rec = eo3d.Reconstructor(seq.camera, config=cfg)
    report = RealtimeClock(speed=0.5).run(rec, (seq.frame(i) for i in range(len(seq))))
    assert report.released == 12 and report.integrated + report.dropped == 12
    assert rec.stats.updates > 0 and len(rec.gmap) > 0 and rec.backlog == 0
    assert rec.fidelity.period_s == pytest.approx(1 / 30 / 0.5)
    assert rec.fidelity.trace and rec.fidelity.trace[-1]["update"] == rec.stats.updates


def test_cost_model_fit_recovers_the_constants_of_noisy_timings():
    truth = CostModel(update_s=0.004, gaussian_s=1e-6, pixel_s=6e-7, pixel_gaussian_s=3e-11, frame_s=0.002)
    rng = np.random.default_rng(0)
    pixels = rng.choice([4800, 19200, 76800, 307200], 400)
    gaussians = rng.integers(1000, 20000, 400)
    seconds = np.array([truth.update(p, g) for p, g in zip(pixels, gaussians)]) * rng.uniform(0.97, 1.03, 400)
    fg = rng.integers(1000, 20000, 50)
    frames = np.stack([fg, [truth.frame(g) for g in fg]], 1)
    fit = CostModel.fit(np.stack([pixels, gaussians, seconds], 1), frames)
    for name in ("update_s", "gaussian_s", "pixel_s", "pixel_gaussian_s", "frame_s"):
        assert getattr(fit, name) == pytest.approx(getattr(truth, name), rel=0.15), name
    # a term the timings do not support is clamped at zero, never negative
    flat = CostModel.fit(np.stack([pixels, gaussians, np.full(400, 0.01)], 1), frames[:0])
    assert flat.update_s == pytest.approx(0.01, rel=1e-6)
    assert min(flat.gaussian_s, flat.pixel_s, flat.pixel_gaussian_s) >= 0.0
    with pytest.raises(ValueError, match="update timings"):
        CostModel.fit(np.zeros((2, 3)), frames)


def test_fixed_updates_clock_prices_the_first_frame_with_the_cost_model_too():
    """Under the updates clock the fidelity policy must never fall back to measured seconds: before this fix the
    first frame's updates were priced by wall time (no period known yet), so a run's map depended on whether the
    kernels were already compiled and on the machine's load (two equal runs in one process differed)."""
    rec = StubMapper()
    order = []
    integrate = rec.integrate
    rec.integrate = lambda frame, *a, **kw: (order.append(("integrate", frame.index, len(rec.attached))),
                                             integrate(frame, *a, **kw))
    cost = CostModel()
    BudgetClock(updates_per_frame=2, cost=cost).run(rec, _frames(3))
    assert order[0] == ("integrate", 0, 1)  # the load (period and cost model) reached the mapper before frame 0
    assert all(c is cost for _, c in rec.attached)
    assert rec.attached[0][0] == pytest.approx(1 / 30)  # the default period until two stamps give the recording's
    assert rec.attached[-1][0] == pytest.approx(1 / 100)


def test_cost_feedback_follows_the_measured_work():
    # updates that take 6 ms of wall time, modelled at 3 ms: without feedback the clock grants the modelled
    # count; with it the correction converges to the measured / modelled ratio (~2) and the budget halves
    cost = CostModel(update_s=0.003, gaussian_s=0.0, pixel_s=0.0, pixel_gaussian_s=0.0, frame_s=0.0)

    def run(feedback):
        rec = StubMapper(update_s=0.006)
        report = BudgetClock(cost=cost, queue_size=4, feedback=feedback).run(rec, _frames(15, fps=20.0))
        return report, rec

    (plain, m_plain), (fed, m_fed) = run(0.0), run(0.3)
    assert plain.cost_factor == 1.0 and fed.cost_factor > 1.5  # sleep overshoots, so measured >= 2x modelled
    assert m_fed.stats.updates < 0.75 * m_plain.stats.updates
    # the policies plan with the corrected model too
    assert m_fed.attached[-1][1].update(1000, 100) == pytest.approx(0.003 * fed.cost_factor, rel=0.5)
    with pytest.raises(ValueError, match="cost_feedback"):
        get_clock(eo3d.Config(clock=ClockConfig(cost_feedback=1.5)))
