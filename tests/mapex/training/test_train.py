"""A few-step training run (seconds), checkpoint/resume, and the data rules."""

import dataclasses

import numpy as np
import pytest
import torch
from tiny_training import PROCEDURAL_ONLY, SMALL, TINY, tiny_overrides, tiny_snapshots

import mapex.training.train as train
from mapex.config import ConfigError, apply_overrides
from mapex.prediction.config import PredictorTrainingConfig
from mapex.prediction.network import OUTSIDE_MAP
from mapex.prediction.weights import MEMBER_NAMES, WeightsError, load_member, read_metadata
from mapex.training.dataset import (
    CropSampler,
    SnapshotSet,
    cached_snapshots,
    training_world_specs,
)
from mapex.worlds import World, load_world
from mapex.worlds.data import HOUSEEXPO_PLANS, IPA_DIR


@pytest.fixture(scope="module")
def snapshots():
    return tiny_snapshots()


def test_snapshots_are_partial_observations(snapshots):
    assert len(snapshots.observed) == 3
    known = [np.count_nonzero(o != 1) for o in snapshots.observed]
    assert known == sorted(known) and known[0] > 0  # the robot keeps seeing more


def test_crops_are_augmented_consistently(snapshots):
    sampler = CropSampler(snapshots, dataclasses.replace(TINY, frontier_share=1.0))
    observed, walls, mask = sampler.sample(np.random.default_rng(0))
    assert observed.shape == walls.shape == mask.shape == (64, 64)
    assert (mask <= (observed == 1)).all()  # the loss only covers unknown cells
    assert not (walls.astype(bool) & (observed == 0)).any()  # free cells are never walls


@pytest.mark.parametrize("overhang", [0, 16])
def test_crops_hang_over_the_map_border_by_at_most_the_overhang(snapshots, overhang):
    config = dataclasses.replace(TINY, frontier_share=0.0, edge_overhang_cells=overhang)
    sampler = CropSampler(snapshots, config)
    rng = np.random.default_rng(1)
    outside_rows_or_cols = []
    for _ in range(200):
        observed, walls, mask = sampler.sample(rng)
        outside = observed == OUTSIDE_MAP
        assert not (mask.astype(bool) & outside).any() and not walls[outside].any()
        outside_rows_or_cols.append(max(outside.all(axis=0).sum(), outside.all(axis=1).sum()))
    assert max(outside_rows_or_cols) == overhang  # the map (>= 150 cells) fills 64-cell crops


def test_a_few_training_steps_write_loadable_weights(snapshots, tmp_path):
    path = train.train_member(0, snapshots, TINY, torch.device("cpu"), tmp_path, False)
    model = load_member(path)
    assert model.config == SMALL
    metadata = read_metadata(path)
    assert metadata["steps"] == 4 and metadata["snapshots"] == 3


@pytest.mark.parametrize("steps", [1, 2, 3, 10, 20])
def test_short_runs_train_whatever_their_length(snapshots, tmp_path, steps):
    path = _train(snapshots, dataclasses.replace(TINY, main_steps=steps), tmp_path)
    assert read_metadata(path)["steps"] == steps


@pytest.mark.parametrize("steps", [1200, 1500, 6000])
def test_the_shipped_run_lengths_warm_up_for_a_tenth_of_their_steps(steps):
    assert train.warmup_fraction(steps, 0.1) == 0.1


def _train(snapshots, config, out_dir, resume=False):
    return train.train_member(0, snapshots, config, torch.device("cpu"), out_dir, resume)


def _assert_same_weights(first_path, second_path):
    first, second = load_member(first_path).state_dict(), load_member(second_path).state_dict()
    for key in first:
        torch.testing.assert_close(first[key], second[key], rtol=0, atol=0)


@pytest.mark.parametrize("data_workers", [0, 2])
def test_interrupted_training_resumes_to_the_same_weights(
    snapshots, tmp_path, monkeypatch, data_workers
):
    config = dataclasses.replace(
        TINY, data_workers=data_workers, main_steps=5, checkpoint_every_steps=3
    )  # resumes at step 3: with 2 workers, worker 0 then serves the odd batches
    straight = _train(snapshots, config, tmp_path / "a")
    resumed = _interrupted_and_resumed(
        lambda resume: _train(snapshots, config, tmp_path / "b", resume), monkeypatch
    )
    _assert_same_weights(straight, resumed)


def _interrupted_and_resumed(run, monkeypatch):
    """`run(resume=False)` stopped by a Ctrl-C in its 5th step, then `run(resume=True)`."""
    real_loss, calls = train.masked_loss, []

    def dying_loss(*args):
        calls.append(1)
        if len(calls) == 5:
            raise KeyboardInterrupt
        return real_loss(*args)

    monkeypatch.setattr(train, "masked_loss", dying_loss)
    with pytest.raises(KeyboardInterrupt):
        run(False)
    monkeypatch.setattr(train, "masked_loss", real_loss)
    return run(True)


def test_loader_workers_draw_a_seeded_order(snapshots, tmp_path):
    config = dataclasses.replace(TINY, data_workers=2)
    first, second = (
        _train(snapshots, config, tmp_path / "a"),
        _train(snapshots, config, tmp_path / "b"),
    )
    _assert_same_weights(first, second)  # the same, however the workers were scheduled
    alone = load_member(_train(snapshots, TINY, tmp_path / "c")).state_dict()
    assert not torch.equal(load_member(first).state_dict()["stem.1.weight"], alone["stem.1.weight"])


def test_each_precision_trains_deterministically_and_they_differ(snapshots, tmp_path):
    mixed_config = apply_overrides(TINY, ["precision=bfloat16"])
    plain = [_train(snapshots, TINY, tmp_path / name) for name in ("a", "b")]  # float32
    mixed = [_train(snapshots, mixed_config, tmp_path / name) for name in ("c", "d")]
    _assert_same_weights(*plain)
    _assert_same_weights(*mixed)
    stem = [load_member(path).state_dict()["stem.1.weight"] for path in (plain[0], mixed[0])]
    assert TINY.precision == "float32" and not torch.equal(*stem)


def test_an_unknown_precision_is_refused():
    with pytest.raises(ConfigError, match="choose one of"):
        apply_overrides(TINY, ["precision=float16"])


def test_the_network_size_is_set_from_the_command_line(snapshots, tmp_path):
    config = apply_overrides(TINY, ["network.channels=8", "network.n_blocks=2"])
    model = load_member(_train(snapshots, config, tmp_path))
    assert (model.config.channels, len(model.blocks)) == (8, 2)


def test_validation_maps_are_refused_for_training():
    with pytest.raises(ValueError, match="validation map"):
        training_world_specs(TINY, ["../shared/data/kth_dev/50052748"])


def test_members_train_on_disjoint_worlds():
    observed = [np.zeros((4, 4), dtype=np.uint8)] * 9
    worlds = [load_world(f"generated:{i}") for i in range(3)]
    data = SnapshotSet(worlds, observed, np.repeat(np.arange(3), 3))
    seen = [set(train.member_snapshots(data, k).world_of) for k in (1, 2, 3)]
    assert seen == [{0}, {1}, {2}]
    assert set(train.member_snapshots(data, 0).world_of) == {0, 1, 2}


def _named_world(name: str) -> World:
    return World(name, np.zeros((4, 4), bool), np.ones((4, 4), bool))


def test_by_source_members_train_on_houseexpo_ipa_and_kth_with_procedural():
    names = ["generated-open:1", "houseexpo-corridor:0", "office_a", "50015847", "houseexpo:7"]
    data = SnapshotSet(
        [_named_world(n) for n in names],
        [np.zeros((4, 4), dtype=np.uint8)] * 10,
        np.repeat(np.arange(5), 2),
    )
    sources = PredictorTrainingConfig().member_sources
    seen = [set(train.member_snapshots(data, k, "by_source", sources).world_of) for k in (1, 2, 3)]
    assert seen == [{1, 4}, {2}, {0, 3}]


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("member_sources=ipa,kth", "member_sources=ipa,kth: give one entry per member (3)"),
        ("member_sources=ipa,kth,moon", "member_sources: unknown source(s) ['moon']"),
    ],
)
def test_bad_member_sources_are_one_line_errors(setting, message, tmp_path, capsys):
    status = train.main(["--out", str(tmp_path), *PROCEDURAL_ONLY, "--set", setting])
    error = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(error) == 1 and message in error[0]


def test_by_source_without_a_members_source_is_refused_before_any_work(tmp_path, capsys):
    status = train.main(
        ["--out", str(tmp_path), *PROCEDURAL_ONLY, "--set", "member_split=by_source"]
    )
    error = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and error == [
        "mapex.training.train: error: g1 trains on houseexpo, but no training world comes "
        "from there (have: procedural): give those maps or other sources"
    ]


def test_members_use_their_own_loss_and_only_the_polish_adds_soft_iou(
    snapshots, tmp_path, monkeypatch
):
    weights = []
    real_loss = train.masked_loss
    monkeypatch.setattr(train, "masked_loss", lambda *a: weights.append(a[3:5]) or real_loss(*a))
    config = dataclasses.replace(
        TINY, wall_weight=2.0, member_wall_weight=1.0, polish_soft_iou_weight=3.0
    )
    for member in (0, 1):
        train.train_member(member, snapshots, config, torch.device("cpu"), tmp_path, False)
    train.polish_main(snapshots, config, torch.device("cpu"), tmp_path, False)
    main, member, polish = np.split(
        np.array(weights), np.cumsum([TINY.main_steps, TINY.member_steps])
    )
    assert {tuple(w) for w in main} == {(2.0, 0.0)}  # wall weight, soft IoU weight
    assert {tuple(w) for w in member} == {(1.0, 0.0)}
    assert {tuple(w) for w in polish} == {(2.0, 3.0)} and len(polish) == TINY.main_polish_steps


def test_polish_only_polishes_the_base_in_out_and_calibrates(snapshots, tmp_path, capsys):
    base_path = _train(snapshots, TINY, tmp_path)
    base = load_member(base_path).state_dict()
    argv = ["--polish-only", "--out", str(tmp_path), *PROCEDURAL_ONLY, *tiny_overrides()]
    assert train.main(argv) == 0
    polished = load_member(tmp_path / "g.pt").state_dict()
    assert not torch.equal(polished["stem.1.weight"], base["stem.1.weight"])
    _assert_same_weights(base_path, train.base_weights(tmp_path))
    assert "calibration" in read_metadata(tmp_path / "g.pt")
    assert capsys.readouterr().out.splitlines()[-1].startswith("g's threshold: ")


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--polish-only"], "no weights file"),
        (["--polish-only", "--calibrate-only"], "--calibrate-only and --polish-only: give one"),
    ],
)
def test_polish_only_refusals_are_one_line_errors(flags, message, tmp_path, capsys):
    status = train.main([*flags, "--out", str(tmp_path), *PROCEDURAL_ONLY])
    error = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(error) == 1 and message in error[0]


def test_polishing_changes_g_but_not_the_base_its_members_start_from(snapshots, tmp_path):
    base_path = _train(snapshots, TINY, tmp_path)
    assert base_path == train.base_weights(tmp_path)
    base = load_member(base_path).state_dict()
    polished_path = train.polish_main(snapshots, TINY, torch.device("cpu"), tmp_path, False)
    polished = load_member(polished_path).state_dict()
    assert polished_path.name == "g.pt" and not torch.equal(
        polished["stem.1.weight"], base["stem.1.weight"]
    )
    _assert_same_weights(base_path, train.base_weights(tmp_path))  # left as it was
    from_main = dataclasses.replace(TINY, members_from_main=True)
    member = train._initial_model(1, from_main, tmp_path).state_dict()
    torch.testing.assert_close(member["stem.1.weight"], base["stem.1.weight"], rtol=0, atol=0)
    fresh = train._initial_model(1, dataclasses.replace(TINY, members_from_main=False), tmp_path)
    assert not torch.equal(fresh.state_dict()["stem.1.weight"], base["stem.1.weight"])
    metadata = read_metadata(polished_path)
    assert metadata["steps"] == TINY.main_steps
    assert metadata["polish_steps"] == TINY.main_polish_steps


def test_without_polish_g_is_its_base(snapshots, tmp_path):
    config = dataclasses.replace(TINY, main_polish_steps=0)
    base_path = _train(snapshots, config, tmp_path)
    _assert_same_weights(
        base_path, train.polish_main(snapshots, config, torch.device("cpu"), tmp_path, False)
    )


@pytest.mark.parametrize(("polish_runs", "steps"), [(1, 5), (2, 4)])  # Ctrl-C in run 0 / 1
def test_an_interrupted_polish_resumes_to_the_same_weights(
    snapshots, tmp_path, monkeypatch, polish_runs, steps
):
    config = dataclasses.replace(
        TINY, main_polish_steps=steps, checkpoint_every_steps=3, polish_runs=polish_runs
    )
    cpu = torch.device("cpu")
    for out in (tmp_path / "a", tmp_path / "b"):
        _train(snapshots, config, out)
    straight = train.polish_main(snapshots, config, cpu, tmp_path / "a", False)
    resumed = _interrupted_and_resumed(
        lambda resume: train.polish_main(snapshots, config, cpu, tmp_path / "b", resume),
        monkeypatch,
    )
    _assert_same_weights(straight, resumed)


def test_several_polish_runs_average_their_weights(snapshots, tmp_path):
    cpu = torch.device("cpu")
    runs = []
    for run in range(2):  # run k of a soup polishes with seed + 4 + k
        config = dataclasses.replace(TINY, seed=run)
        _train(snapshots, TINY, tmp_path / f"run{run}")
        runs.append(
            load_member(train.polish_main(snapshots, config, cpu, tmp_path / f"run{run}", False))
        )
    _train(snapshots, TINY, tmp_path / "soup")
    config = dataclasses.replace(TINY, polish_runs=2)
    soup_path = train.polish_main(snapshots, config, cpu, tmp_path / "soup", False)
    soup = load_member(soup_path).state_dict()
    first, second = (model.state_dict() for model in runs)
    assert not torch.equal(first["stem.1.weight"], second["stem.1.weight"])
    for key, value in soup.items():
        mean = (first[key] + second[key]) / 2 if value.is_floating_point() else first[key]
        torch.testing.assert_close(value, mean, rtol=0, atol=2e-3)
    metadata = read_metadata(soup_path)
    assert metadata["polish_runs"] == 2
    assert metadata["polish_training_config"] == dataclasses.asdict(config)


def test_mean_state_dict_averages_floats_and_keeps_counters():
    states = [
        {"w": torch.tensor([1.0, 2.0]), "n": torch.tensor(3)},
        {"w": torch.tensor([3.0, 6.0]), "n": torch.tensor(5)},
    ]
    mean = train.mean_state_dict(states)
    assert torch.equal(mean["w"], torch.tensor([2.0, 4.0])) and mean["n"].item() == 3


@pytest.mark.parametrize(
    "setting, message",
    [
        ("polish_runs=0", "polish_runs must be >= 1, got 0"),
        ("main_steps=-5", "main_steps must be >= 0, got -5"),
        ("main_polish_steps=-1", "main_polish_steps must be >= 0, got -1"),
        ("warmup_share=1.5", "warmup_share must be in (0, 1), got 1.5"),
    ],
)
def test_impossible_schedules_are_one_line_errors(setting, message, tmp_path, capsys):
    status = train.main(["--out", str(tmp_path), *PROCEDURAL_ONLY, "--set", setting])
    error = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and error == [f"mapex.training.train: error: {message}"]


def _wall_crops() -> tuple[torch.Tensor, torch.Tensor]:
    """Two 1x4x4 crops: walls in the left column, loss over all cells but the right column."""
    walls = torch.zeros(2, 1, 4, 4)
    walls[..., 0] = 1.0
    mask = torch.ones(2, 1, 4, 4)
    mask[..., 3] = 0.0
    return walls, mask


def test_soft_iou_loss_is_near_zero_when_right_and_near_one_when_wrong():
    walls, mask = _wall_crops()
    sure = 20.0 * (2.0 * walls - 1.0)  # logits: confident walls where the walls are
    assert train.soft_iou_loss(sure, walls, mask).item() < 1e-3
    assert train.soft_iou_loss(-sure, walls, mask).item() > 0.9


def test_soft_iou_loss_ignores_cells_outside_the_mask():
    walls, mask = _wall_crops()
    logits = torch.randn(2, 1, 4, 4, generator=torch.Generator().manual_seed(0))
    changed = logits.clone()
    changed[..., 3] = 50.0  # confident walls, but outside the mask
    assert train.soft_iou_loss(changed, walls, mask) == train.soft_iou_loss(logits, walls, mask)


def test_soft_iou_loss_of_a_crop_without_walls_is_zero():
    empty = torch.zeros(1, 1, 4, 4)
    assert train.soft_iou_loss(torch.full_like(empty, -20.0), empty, torch.ones_like(empty)) < 1e-6


def test_free_outside_plans_are_explored_as_generated_open_worlds():
    config = dataclasses.replace(TINY, free_outside_plans=True, procedural_worlds=2)
    assert training_world_specs(config, []) == [
        f"generated-open:{config.first_procedural_seed + i}" for i in range(2)
    ]


def test_members_start_from_the_trained_main_model(snapshots, tmp_path):
    main = load_member(train.train_member(0, snapshots, TINY, torch.device("cpu"), tmp_path, False))
    member = train._initial_model(1, TINY, tmp_path)
    for key, value in main.state_dict().items():
        torch.testing.assert_close(member.state_dict()[key], value, rtol=0, atol=0)
    assert member.training  # ready to be fine-tuned
    fresh = train._initial_model(1, dataclasses.replace(TINY, members_from_main=False), tmp_path)
    weight = "stem.1.weight"
    assert not torch.equal(fresh.state_dict()[weight], main.state_dict()[weight])


def test_a_member_without_a_trained_main_model_is_refused(tmp_path):
    with pytest.raises(WeightsError, match="no weights file"):
        train._initial_model(2, TINY, tmp_path)


def test_a_main_model_of_another_size_is_refused(snapshots, tmp_path):
    train.train_member(0, snapshots, TINY, torch.device("cpu"), tmp_path, False)
    other = apply_overrides(TINY, ["network.channels=8"])
    with pytest.raises(ValueError, match="another network size"):
        train._initial_model(3, other, tmp_path)


def test_members_without_g_are_refused_before_any_work(tmp_path, capsys):
    status = train.main(["--members", "g2,g3", "--out", str(tmp_path), *PROCEDURAL_ONLY])
    error = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and error == [
        "mapex.training.train: error: g2, g3 would start from G's weights, "
        f"but there is no {tmp_path / 'g-base.pt'}: train g too (--members g,g1,g2,g3) "
        "or --set members_from_main=false"
    ]  # one line, and no snapshots were collected


def test_too_few_worlds_for_the_members_are_refused_before_any_work(tmp_path, capsys):
    argv = ["--out", str(tmp_path), *PROCEDURAL_ONLY, "--set", "procedural_worlds=2"]
    status = train.main(argv)
    error = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and error == [
        "mapex.training.train: error: 2 training world(s), but g, g1, g2, g3 need at least 3: "
        "raise procedural_worlds or give the KTH maps"
    ]


@pytest.mark.parametrize("emulated", [True, False])
def test_training_warns_once_where_bfloat16_is_emulated(emulated, monkeypatch, capsys):
    monkeypatch.setattr(train, "emulated_bfloat16", lambda device, precision: emulated)
    train._warn_if_emulated_bfloat16(torch.device("cpu"), TINY)
    warning = capsys.readouterr().err.strip().splitlines()
    assert len(warning) == int(emulated)
    assert all("--set precision=float32" in line for line in warning)


def test_a_few_steps_train_every_member_on_houseexpo_ipa_and_procedural_worlds(tmp_path):
    if not (HOUSEEXPO_PLANS.is_file() and (IPA_DIR / "freiburg_building101").is_dir()):
        pytest.skip("../shared/data/houseexpo or ipa is not present")
    sources = ["--set", "houseexpo_worlds=1", "--set", "use_ipa=true"]
    sources += ["--set", "ipa_maps=freiburg_building101", "--set", "calibration_snapshots=4"]
    sources += [
        "--set",
        "member_sources=houseexpo,ipa,procedural",
        "--set",
        "member_split=by_source",
        "--set",
        "snapshot_every_steps=10",
    ]
    argv = ["--out", str(tmp_path), "--no-kth", *tiny_overrides(), *sources]
    assert train.main(argv) == 0
    worlds = {name: read_metadata(tmp_path / f"{name}.pt")["worlds"] for name in MEMBER_NAMES}
    assert worlds["g"] == ["freiburg_building101", "generated-open:1000", "houseexpo-corridor:0"]
    assert [worlds[name] for name in MEMBER_NAMES[1:]] == [
        ["houseexpo-corridor:0"],
        ["freiburg_building101"],
        ["generated-open:1000"],
    ]


def test_a_validation_map_named_in_ipa_maps_is_refused_before_any_work(tmp_path, capsys):
    argv = ["--out", str(tmp_path), *PROCEDURAL_ONLY, "--set", "use_ipa=true"]
    assert train.main([*argv, "--set", "ipa_maps=office_a,NLB"]) == 2
    assert capsys.readouterr().err.strip() == (
        "mapex.training.train: error: NLB is a validation map (mapex.worlds.data): "
        "never train on it"
    )


def test_bagged_members_each_see_their_own_share_of_every_source():
    names = [f"generated-open:{i}" for i in range(6)] + [
        f"houseexpo-corridor:{i}" for i in range(3)
    ]
    data = SnapshotSet(
        [_named_world(n) for n in names],
        [np.zeros((4, 4), dtype=np.uint8)] * 9,
        np.arange(9),
    )
    bags = [
        set(train.member_snapshots(data, k, "bagged", (), 0.67, seed=0).world_of) for k in (1, 2, 3)
    ]
    for bag in bags:
        assert len(bag & set(range(6))) == 4 and len(bag & {6, 7, 8}) == 2  # 2/3 of each source
    assert len({frozenset(bag) for bag in bags}) == 3  # a draw of its own per member
    again = set(train.member_snapshots(data, 1, "bagged", (), 0.67, seed=0).world_of)
    assert again == bags[0]  # seeded


def test_kth_sdf_training_floors_leave_out_held_out_flagged_and_kth_dev_floors(tmp_path):
    for floor in ("50015847", "50053292", "0510032192_A_40_1_203", "50099999", "50037764_PLAN1"):
        (tmp_path / f"{floor}.world").write_text("<sdf/>")
    specs = train.kth_sdf_specs(tmp_path)
    assert specs == [f"{tmp_path / '50099999'}.world@scale=0.5,frame=drop"]
    (tmp_path / "50099999.world").unlink()
    with pytest.raises(ValueError, match="no trainable"):
        train.kth_sdf_specs(tmp_path)


def test_snapshots_are_kept_and_read_back_for_the_same_data_only(tmp_path, capsys):
    specs = training_world_specs(TINY, [])
    path = tmp_path / "snapshots.npz"
    first = cached_snapshots(path, specs, TINY)
    again = cached_snapshots(path, specs, TINY)
    assert "read from" in capsys.readouterr().err
    assert len(again.observed) == len(first.observed)
    assert all(np.array_equal(a, b) for a, b in zip(first.observed, again.observed, strict=True))
    assert np.array_equal(first.world_of, again.world_of)
    other = dataclasses.replace(TINY, snapshot_every_steps=60)
    cached_snapshots(path, specs, other)
    assert "holds other snapshots" in capsys.readouterr().err


def test_far_cells_are_those_beyond_far_cells_of_every_known_cell():
    inputs = torch.zeros(1, 3, 30, 30)
    inputs[0, 2] = 1.0  # all unknown
    inputs[0, 2, 5, 5], inputs[0, 0, 5, 5] = 0.0, 1.0  # one known free cell
    far = train.far_from_known(inputs, torch.ones(1, 1, 30, 30), far_cells=10)
    assert far[0, 0, 15, 5] == 0 and far[0, 0, 16, 5] == 1  # 10 cells away is near
    assert far[0, 0, 5, 15] == 0 and far[0, 0, 16, 16] == 1
    assert far[0, 0, 5, 5] == 0


def test_the_far_soft_iou_adds_a_loss_over_the_far_cells_only():
    logits = torch.full((1, 1, 8, 8), -12.0)  # predicts no wall anywhere
    walls = torch.zeros(1, 1, 8, 8)
    walls[..., 6, :] = 1.0  # a wall in the far rows only
    mask = torch.ones(1, 1, 8, 8)
    far = torch.zeros(1, 1, 8, 8)
    far[..., 5:, :] = 1.0
    plain = train.masked_loss(logits, walls, mask, 2.0)
    with_far = train.masked_loss(logits, walls, mask, 2.0, 0.0, 3.0, far)
    assert with_far.item() == pytest.approx(plain.item() + 3 * (1 - 1 / 9), rel=1e-3)
    near_only = torch.zeros_like(far)
    near_only[..., :2, :] = 1.0  # no wall there, none predicted: nothing to add
    assert train.masked_loss(logits, walls, mask, 2.0, 0.0, 3.0, near_only).item() == (
        pytest.approx(plain.item(), rel=1e-3)
    )
