"""Teams of robots (mapex.team): starts, claims, the team methods and the team loop."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mapex.config import ExplorationConfig, TeamConfig
from mapex.episode import run_episode
from mapex.grid import FREE, UNKNOWN
from mapex.methods import METHODS, TEAM_METHODS, make_method
from mapex.methods.base import PlanningContext
from mapex.methods.claims import Claim, ClaimBoard
from mapex.prediction import make_predictor
from mapex.prediction.base import EnsemblePrediction
from mapex.team.shared_prediction import EpochPrediction
from mapex.team.starts import team_start_cells
from mapex.worlds import WorldError, load_world

CONFIG = ExplorationConfig(steps=120)


# ----------------------------------------------------------------------------- starts


def test_a_team_deploys_spaced_around_the_start(world):
    cells = team_start_cells(world, [1], 4, CONFIG)
    assert cells[0] == team_start_cells(world, [1], 1, CONFIG)[0]
    gaps = [np.hypot(*np.subtract(a, b)) for i, a in enumerate(cells) for b in cells[:i]]
    assert min(gaps) >= CONFIG.team.spacing_cells
    assert max(np.hypot(*np.subtract(c, cells[0])) for c in cells) < 4 * CONFIG.team.spacing_cells
    assert all(not world.occupancy[c] and world.valid_space[c] for c in cells)


def test_explicit_starts_are_taken_as_given_and_bad_counts_refused(world):
    first, second = team_start_cells(world, [0], 2, CONFIG)
    assert team_start_cells(world, [second, first], 2, CONFIG) == [second, first]
    with pytest.raises(WorldError, match="3 starts given for 2 robots"):
        team_start_cells(world, [0, 1, 2], 2, CONFIG)


def test_a_team_that_does_not_fit_is_a_one_line_error(world):
    crowded = ExplorationConfig(team=TeamConfig(spacing_cells=10**4))
    with pytest.raises(WorldError, match="room for 1 robots") as error:
        team_start_cells(world, [0], 2, crowded)
    assert "\n" not in str(error.value) and "team.spacing_cells" in str(error.value)


# ----------------------------------------------------------------------------- claims


def _context(config: ExplorationConfig) -> PlanningContext:
    """A corridor seen from its middle: unknown to the left and to the right."""
    observed = np.full((21, 61), UNKNOWN, dtype=np.uint8)
    observed[8:13, 20:41] = FREE
    cost = np.where(observed == FREE, 1.0, np.inf).astype(np.float32)
    return PlanningContext(
        observed=observed, pose=np.array([10, 30]), frontiers=np.array([[10, 20], [10, 40]]),
        prediction=None, cost=cost, reachable=observed == FREE, config=config,
        rng=np.random.default_rng(0),
    )  # fmt: skip


def test_claimed_cells_are_worth_nothing_to_teammates():
    context = _context(CONFIG)
    claimed = np.zeros(context.observed.shape, dtype=bool)
    claimed[:, :30] = True
    weights = PlanningContext(**{**context.__dict__, "claimed": claimed}).unknown_weights(1.0)
    assert weights[:, :30].sum() == 0 and weights[0, 40] == 1.0
    assert context.unknown_weights(1.0)[0, 0] == 1.0  # no claims: every unknown cell counts


def test_nearest_team_keeps_away_from_a_teammates_goal():
    method = make_method("nearest_team", CONFIG)
    context = _context(CONFIG)
    alone = method.select_goal(context)
    method.teammates = [Claim(1, 0, tuple(alone.cell), 1.0, np.zeros((21, 61), bool))]
    other = method.select_goal(context)
    assert not np.array_equal(other.frontier, alone.frontier)
    claim = method.claim_of(0, 5)
    assert claim.goal == tuple(other.cell) and claim.t == 5 and not claim.visible.any()


@pytest.mark.parametrize("every", [0, 4])
def test_mapex_team_claims_the_goals_visible_set_and_with_path_claims_the_way_there(every):
    config = replace(
        CONFIG,
        visibility=replace(CONFIG.visibility, range_cells=6),
        team=TeamConfig(claim_path_every_cells=every),
    )
    context = _context(config)
    members = np.zeros((4, *context.observed.shape), np.float32)
    members[1, :, 35:] = 0.1  # the members disagree right of col 35 only: goal (10, 40)
    method = make_method("mapex_team", config)
    goal = method.select_goal(replace(context, prediction=EnsemblePrediction(members)))
    visible = method.claim_of(0, 3).visible
    assert tuple(goal.frontier) == (10, 40)
    assert visible[4, 40] and not visible[8:13, :41].any()  # unknown cells only
    assert not visible[:, :25].any()  # nothing on the far side
    assert visible[4, 34] == (every > 0)  # seen from (10, 34) on the way, out of the goal's range

    method = make_method("mapex_independent", CONFIG)
    assert not method.coordinates and method.claim_of(0, 0) is None


def test_the_board_keeps_the_latest_claim_of_each_robot():
    board = ClaimBoard((3, 3), conflict_cells=2)
    visible = np.zeros((3, 3), bool)
    visible[0, 0] = True
    board.post(Claim(0, 1, (1, 1), 2.0, visible))
    board.post(Claim(2, 1, (2, 2), 1.0, np.zeros((3, 3), bool)))
    board.post(Claim(0, 4, (0, 1), 3.0, np.zeros((3, 3), bool)))
    assert [c.robot for c in board.teammates_of(1)] == [0, 2]
    assert board.of(0).t == 4 and not board.claimed_by_teammates(2).any()
    board.withdraw(0)
    assert [c.robot for c in board.teammates_of(1)] == [2]


def _claim(robot: int, goal, score: float) -> Claim:
    return Claim(robot, 0, goal, score, np.zeros((30, 30), bool))


def test_a_better_claim_nearby_makes_the_holder_drop_its_goal():
    board = ClaimBoard((30, 30), conflict_cells=5)
    assert board.settle({0: _claim(0, (10, 10), 1.0), 1: _claim(1, (25, 25), 1.0)}) == []
    assert board.settle({2: _claim(2, (12, 12), 2.0)}) == [0]  # near robot 0's, better
    assert board.of(0) is None and board.of(1) is not None
    assert board.settle({3: _claim(3, (24, 24), 0.5)}) == []  # near robot 1's, worse
    assert board.settle({1: None}) == [] and board.of(1) is None  # re-planned to no goal


def test_claims_made_at_one_step_settle_the_same_whatever_their_order():
    made = {1: _claim(1, (10, 10), 1.0), 0: _claim(0, (11, 11), 3.0)}
    first, second = ClaimBoard((30, 30), 5), ClaimBoard((30, 30), 5)
    assert first.settle(made) == second.settle(dict(reversed(list(made.items())))) == [1]


def test_only_the_team_methods_coordinate_and_every_method_is_made_for_teams_or_not():
    coordinating = {name for name, method in METHODS.items() if method.coordinates}
    assert coordinating == {"mapex_team", "mapex_plus_team", "nearest_team", "mapex_assign"}
    assert set(TEAM_METHODS) == coordinating | {"mapex_independent", "mapex_voronoi"}


# ----------------------------------------------------------------------------- the loop


@pytest.mark.parametrize("name", sorted(TEAM_METHODS))
def test_seeded_team_episode_is_deterministic(name, world, predictor):
    first = run_episode(world, name, predictor, [1], robots=2, seed=7, config=CONFIG)
    second = run_episode(world, name, predictor, [1], robots=2, seed=7, config=CONFIG)
    for a, b in zip(first.trajectories, second.trajectories, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(first.final_observed, second.final_observed)
    assert first.curves.coverage == second.curves.coverage
    assert first.overlap == second.overlap and first.path_lengths_m == second.path_lengths_m
    assert all(len(path) == CONFIG.steps + 1 or first.finished_at for path in first.trajectories)
    assert first.curves.coverage[-1] > first.curves.coverage[0]


def test_one_independent_robot_is_the_single_robot_run(world, predictor):
    team = run_episode(world, "mapex_independent", predictor, [2], robots=1, seed=3, config=CONFIG)
    alone = run_episode(world, "mapex", predictor, 2, seed=3, config=CONFIG)
    np.testing.assert_array_equal(team.trajectories[0], alone.trajectory)
    assert team.curves.coverage == alone.curves.coverage and team.overlap == 0.0


def test_a_method_that_does_not_coordinate_runs_in_a_team_as_mapex_independent(world, predictor):
    pair = run_episode(world, "mapex", predictor, 2, seed=3, config=CONFIG, robots=2)
    named = run_episode(world, "mapex_independent", predictor, 2, seed=3, config=CONFIG, robots=2)
    for a, b in zip(pair.trajectories, named.trajectories, strict=True):
        np.testing.assert_array_equal(a, b)
    assert pair.curves.coverage == named.curves.coverage and pair.robots == 2
    assert pair.is_team and named.is_team


def test_every_robot_holds_the_merged_map_and_overlap_counts_shared_cells(predictor):
    world = load_world("generated:0")
    result = run_episode(world, "mapex_team", predictor, [0], robots=2, seed=0, config=CONFIG)
    assert 0.0 < result.overlap < 1.0
    assert all(length > 0 for length in result.path_lengths_m)
    assert result.robots == 2 and len(result.robot_stats) == 2
    moved = [np.abs(np.diff(path, axis=0)).max() for path in result.trajectories]
    assert max(moved) <= CONFIG.motion.cells_per_step


# ----------------------------------------------------------------------------- predictions


class _Counting:
    """A predictor that counts its predictions and remembers each map it was given."""

    def __init__(self, inner):
        self.inner, self.maps = inner, []

    def predict(self, observed, region=None, members=None):
        self.maps.append(observed.copy())
        return self.inner.predict(observed, region, members)


def test_the_team_predicts_once_per_epoch_on_the_epochs_map(predictor):
    """Re-plans within an epoch share one prediction made on the map at the epoch's first
    step, with the cells known since copied through; the next epoch predicts again."""
    world = load_world("generated:0")
    maps = [np.full(world.shape, UNKNOWN, dtype=np.uint8) for _ in range(3)]
    for k, observed in enumerate(maps):
        observed[40 : 60 + 10 * k, 40:80] = FREE  # the known area grows step by step
    counting = _Counting(predictor)
    shared = EpochPrediction(counting, epoch_steps=10, margin_cells=20)
    shared.begin_step(10, maps[0])
    first = shared.prediction(maps[0], (0, 1, 2, 3))
    shared.begin_step(11, maps[1])
    later = shared.prediction(maps[1], (0, 1, 2, 3))  # same epoch: no new prediction
    assert len(counting.maps) == 1 and np.array_equal(counting.maps[0], maps[0])
    np.testing.assert_array_equal(later.members, first.with_known(maps[1]).members)
    shared.begin_step(20, maps[2])
    shared.prediction(maps[2], (0, 1, 2, 3))
    assert len(counting.maps) == 2 and np.array_equal(counting.maps[1], maps[2])


@pytest.mark.parametrize("epoch_steps", [1, 10])
def test_epoch_predictions_keep_team_runs_deterministic(world, predictor, epoch_steps):
    config = replace(CONFIG, team=TeamConfig(prediction_epoch_steps=epoch_steps))
    runs = [
        run_episode(world, "mapex_team", predictor, [1], robots=2, seed=5, config=config)
        for _ in range(2)
    ]
    for a, b in zip(runs[0].trajectories, runs[1].trajectories, strict=True):
        np.testing.assert_array_equal(a, b)
    assert runs[0].curves.coverage == runs[1].curves.coverage
    assert runs[0].curves.coverage[-1] > runs[0].curves.coverage[0]


@pytest.mark.parametrize("name", sorted(n for n in TEAM_METHODS if METHODS[n].uses_prediction))
def test_a_team_on_the_oracle_shares_the_truth_and_is_never_degraded(world, name):
    """The team's epoch prediction is the oracle's, with the cells known since copied
    through (`OraclePrediction.with_known`): every re-plan answered, runs repeatable."""
    oracle, config = make_predictor("oracle", world.occupancy), replace(CONFIG, steps=80)
    runs = [run_episode(world, name, oracle, [1], robots=2, seed=5, config=config) for _ in "ab"]
    for a, b in zip(runs[0].trajectories, runs[1].trajectories, strict=True):
        np.testing.assert_array_equal(a, b)
    assert runs[0].curves.coverage == runs[1].curves.coverage
    assert runs[0].curves.coverage[-1] > runs[0].curves.coverage[0]
    assert all(stats.degraded_steps == [] for stats in runs[0].robot_stats)
