"""Triplet sampler statistics: window, same sequence, global pairs, determinism, resume, gaps, short runs."""

from __future__ import annotations

import numpy as np
import pytest

from relocdepth.errors import UserError
from relocdepth.sampler import FrameKey, PairParallax, SamplerConfig, TripletSampler


def _frames() -> list[FrameKey]:
    """seq-a: 120 frames at 30 fps; seq-b: frames 0-9 and 40-59 (a gap); seq-c: 5 frames; seq-d: 2 frames."""
    out = [FrameKey("seq-a", i, i / 30) for i in range(120)]
    out += [FrameKey("seq-b", i, i / 30) for i in [*range(10), *range(40, 60)]]
    out += [FrameKey("seq-c", i, i / 30) for i in range(5)]
    out += [FrameKey("seq-d", i, i / 30) for i in range(2)]
    return out


FRAMES = _frames()


def _all(s: TripletSampler, epoch: int) -> list:
    return list(s.iter_epoch(epoch))


def test_window_same_sequence_distinct() -> None:
    s = TripletSampler(FRAMES, SamplerConfig(window=20, epochs=10, global_epochs=2, seed=3))
    for epoch in (0, 1):
        for t in _all(s, epoch):
            ft = FRAMES[t.target]
            assert len({t.source_a, t.target, t.source_b}) == 3
            assert not t.is_global
            for src in (t.source_a, t.source_b):
                fs = FRAMES[src]
                assert fs.sequence == ft.sequence
                assert abs(fs.frame - ft.frame) <= 20  # distance in frame index


def test_window_reaches_its_bounds() -> None:
    s = TripletSampler(FRAMES, SamplerConfig(window=5, epochs=200, global_epochs=0))
    offsets = [FRAMES[src].frame - FRAMES[t.target].frame
               for e in range(30) for t in _all(s, e) if FRAMES[t.target].sequence == "seq-a"
               for src in (t.source_a, t.source_b)]
    assert set(offsets) == {-5, -4, -3, -2, -1, 1, 2, 3, 4, 5}


def test_gaps_count_as_distance() -> None:
    s = TripletSampler(FRAMES, SamplerConfig(window=20, epochs=50, global_epochs=0))
    for e in range(20):
        for t in _all(s, e):
            ft = FRAMES[t.target]
            if ft.sequence == "seq-b" and ft.frame < 10:  # frames 40+ are >= 31 indices away
                assert all(FRAMES[x].frame < 10 for x in (t.source_a, t.source_b))


def test_short_sequences() -> None:
    s = TripletSampler(FRAMES, SamplerConfig(window=20))
    targets = {FRAMES[i].sequence for i in s.targets(0)}
    assert "seq-c" in targets  # shorter than the window: all of it is nearby
    assert "seq-d" not in targets  # only 2 frames: cannot give two distinct sources
    # One epoch = every eligible training frame once as a target.
    order = [t.target for t in _all(s, 0)]
    assert sorted(order) == sorted(s.targets(0).tolist()) == sorted(set(order))
    assert len(order) == len(FRAMES) - 2


def test_global_fraction_before_and_after_switch() -> None:
    cfg = SamplerConfig(window=20, epochs=10, global_epochs=4, global_prob=0.5, seed=1)
    s = TripletSampler(FRAMES, cfg)
    assert cfg.global_from() == 6
    before = [t.is_global for e in range(6) for t in _all(s, e)]
    after = [t.is_global for e in range(6, 10) for t in _all(s, e)]
    assert not any(before)
    frac = float(np.mean(after))
    assert abs(frac - 0.5) < 4 * np.sqrt(0.25 / len(after))  # binomial, 4 sigma
    cross = [t for e in range(6, 10) for t in _all(s, e)
             if t.is_global and FRAMES[t.source_a].sequence != FRAMES[t.target].sequence]
    assert cross  # global pairs reach other sequences (and seq-d frames can be sources)
    for t in _all(s, 8):
        assert len({t.source_a, t.target, t.source_b}) == 3


def test_window_seconds() -> None:
    s = TripletSampler(FRAMES, SamplerConfig(window=20, window_seconds=0.1, epochs=50, global_epochs=0))
    offs = {FRAMES[x].frame - FRAMES[t.target].frame
            for e in range(10) for t in _all(s, e) if FRAMES[t.target].sequence == "seq-a"
            for x in (t.source_a, t.source_b)}
    assert offs == {-3, -2, -1, 1, 2, 3}  # 0.1 s at 30 fps


def test_window_schedule() -> None:
    cfg = SamplerConfig(window=20, window_schedule=((0, 2), (3, 8)), epochs=10, global_epochs=0)
    assert [cfg.window_at(e) for e in (0, 2, 3, 9)] == [2, 2, 8, 8]
    s = TripletSampler(FRAMES, cfg)
    assert max(abs(FRAMES[t.source_a].frame - FRAMES[t.target].frame) for t in _all(s, 1)) <= 2


def test_deterministic_and_seeded() -> None:
    a = _all(TripletSampler(FRAMES, SamplerConfig(seed=7, epochs=3, global_epochs=1)), 2)
    b = _all(TripletSampler(FRAMES, SamplerConfig(seed=7, epochs=3, global_epochs=1)), 2)
    c = _all(TripletSampler(FRAMES, SamplerConfig(seed=8, epochs=3, global_epochs=1)), 2)
    assert a == b and a != c
    s = TripletSampler(FRAMES, SamplerConfig(seed=7))
    assert _all(s, 0) != _all(s, 1)  # a new permutation every epoch


def test_resume_continues_the_stream() -> None:
    s = TripletSampler(FRAMES, SamplerConfig(seed=2))
    full = _all(s, 4)
    resumed = list(TripletSampler(FRAMES, SamplerConfig(seed=2)).iter_epoch(4, start=37))
    assert resumed == full[37:]


def test_ranks_split_the_epoch() -> None:
    cfg = SamplerConfig(seed=5)
    ranks = [TripletSampler(FRAMES, cfg, rank=r, world_size=3) for r in range(3)]
    streams = [_all(s, 0) for s in ranks]
    assert len({len(x) for x in streams}) == 1  # equal steps per rank (DDP needs it)
    targets = [t.target for x in streams for t in x]
    assert set(targets) == set(TripletSampler(FRAMES, cfg).targets(0).tolist())
    assert len(targets) - len(set(targets)) < 3  # only the padding repeats
    assert streams[0] != streams[1]


def test_bad_configs() -> None:
    with pytest.raises(UserError, match="window"):
        SamplerConfig(window=0)
    with pytest.raises(UserError, match="global-prob"):
        SamplerConfig(global_prob=1.5)
    with pytest.raises(UserError, match="two other frames"):
        TripletSampler([FrameKey("a", 0, 0.0), FrameKey("a", 50, 1.0), FrameKey("b", 0, 0.0)])


# -- --min-parallax --------------------------------------------------------------------------------
# seq-a moves sideways for frames 0-59 (0.5 px of parallax per frame) and only turns for 60-119;
# parallax(i, j) = 0.5 * |x_i - x_j| px with x the distance travelled (in frames).
PX_PER_FRAME = 0.5
OFFSETS = np.array([1, 2, 4, 8, 16, 32])


def _travel(f: FrameKey) -> float:
    return float(min(f.frame, 59)) if f.sequence == "seq-a" else float(f.frame)


def _true_parallax(i: int, j: int) -> float:
    return PX_PER_FRAME * abs(_travel(FRAMES[i]) - _travel(FRAMES[j]))


def _table(frames: list[FrameKey] = FRAMES) -> PairParallax:
    """The forward-pair table ingest would store (NaN past the end of a sequence)."""
    px = np.full((len(frames), len(OFFSETS)), np.nan)
    for i in range(len(frames)):
        for j, k in enumerate(OFFSETS):
            if i + k < len(frames) and frames[i + k].sequence == frames[i].sequence:
                px[i, j] = _true_parallax(i, i + k)
    return PairParallax(OFFSETS, px)


def test_parallax_interpolates_between_stored_offsets() -> None:
    table = _table()
    first = np.array([0, 0, 0, 10, 100, 100])
    gap = np.array([1, 3, 12, 20, 10, 19])  # 100 + 19 = 119: offset 32 is past the end
    got = table.between(first, gap)
    # linear motion: interpolation is exact; past the end the lower stored offset (16) is used
    want = [PX_PER_FRAME * g for g in (1, 3, 12, 20)] + [0.0, 0.0]
    np.testing.assert_allclose(got, want)
    got_end = table.between(np.array([40]), np.array([30]))  # 40 + 32 = 72 is stored
    np.testing.assert_allclose(got_end, [_true_parallax(40, 56) + 14 / 16 * (_true_parallax(40, 72)
                                                                          - _true_parallax(40, 56))])
    clamp = table.between(np.array([0]), np.array([45]))  # beyond the largest offset: its value
    np.testing.assert_allclose(clamp, [PX_PER_FRAME * 32])


def test_min_parallax_sources_have_parallax_or_are_the_largest() -> None:
    cfg = SamplerConfig(window=20, epochs=10, global_epochs=0, seed=4, min_parallax=3.0)
    s = TripletSampler(FRAMES, cfg, parallax=_table())
    seen_fallback = seen_threshold = 0
    for e in range(3):
        for t in _all(s, e):
            if FRAMES[t.target].sequence != "seq-a":  # the one with a known motion model
                continue
            lo, hi = (int(x[t.target]) for x in s.neighbour_range(e))
            cand = [c for c in range(lo, hi) if c != t.target]
            true = {c: _true_parallax(t.target, c) for c in cand}
            assert len({t.source_a, t.target, t.source_b}) == 3
            if sum(v >= 3.0 for v in true.values()) >= 2:
                seen_threshold += 1
                assert true[t.source_a] >= 3.0 and true[t.source_b] >= 3.0
            else:
                seen_fallback += 1
                top2 = sorted(true.values(), reverse=True)[:2]
                assert sorted([true[t.source_a], true[t.source_b]], reverse=True) == top2
    assert seen_threshold > 100 and seen_fallback > 50  # both branches ran
    # Without the option the paper's draw picks small-parallax sources too.
    plain = TripletSampler(FRAMES, SamplerConfig(window=20, epochs=10, global_epochs=0, seed=4))
    gaps = [_true_parallax(t.target, t.source_a) for t in _all(plain, 0) if FRAMES[t.target].frame < 40
            and FRAMES[t.target].sequence == "seq-a"]
    assert min(gaps) < 3.0


def test_min_parallax_is_a_pure_function_of_seed_epoch_position_rank() -> None:
    cfg = SamplerConfig(window=20, epochs=5, global_epochs=2, seed=9, min_parallax=2.0)
    a = TripletSampler(FRAMES, cfg, parallax=_table())
    b = TripletSampler(FRAMES, cfg, parallax=_table())
    assert _all(a, 3) == _all(b, 3)  # global pairs from epoch 3 on are unaffected
    assert list(b.iter_epoch(3, start=20)) == _all(a, 3)[20:]
    # Rank 1 of 2 draws the single process's odd positions, sources included.
    rank1 = _all(TripletSampler(FRAMES, cfg, rank=1, world_size=2, parallax=_table()), 0)
    single = _all(a, 0)[1::2]
    assert len(single) >= len(rank1) - 1
    assert all((x.target, x.source_a, x.source_b) == (y.target, y.source_a, y.source_b)
               for x, y in zip(rank1, single))


def test_default_sampler_ignores_parallax_and_unknown_never_qualifies() -> None:
    cfg = SamplerConfig(seed=3, epochs=4, global_epochs=1)
    assert _all(TripletSampler(FRAMES, cfg, parallax=_table()), 1) == _all(TripletSampler(FRAMES, cfg), 1)
    table = _table()
    px = table.px.copy()
    px[:60] = np.nan  # frames 0-59 of seq-a: tracking failed everywhere
    s = TripletSampler(FRAMES, SamplerConfig(window=3, min_parallax=0.1, seed=1), parallax=PairParallax(OFFSETS, px))
    for t in _all(s, 0):
        if FRAMES[t.target].sequence == "seq-a" and FRAMES[t.target].frame <= 55:
            # nothing known: the paper's draw within the window still gives two distinct sources
            assert len({t.source_a, t.target, t.source_b}) == 3
            assert all(abs(FRAMES[x].frame - FRAMES[t.target].frame) <= 3 for x in (t.source_a, t.source_b))


def test_min_parallax_needs_data_and_a_valid_value() -> None:
    with pytest.raises(UserError, match="add-parallax"):
        TripletSampler(FRAMES, SamplerConfig(min_parallax=1.0))
    with pytest.raises(UserError, match="min-parallax"):
        SamplerConfig(min_parallax=-1.0)
