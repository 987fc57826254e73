"""CL EDMD from episodes of several controllers: ground truth, an independent solve, identifiability.

The plant is common to every episode; each controller's loop differs only by
its known controller (its state count too). Ground truth is a linear plant
with identity lifting and noise-free data, as in test_analytic.py.
"""

import copy

import numpy as np
import pytest

from qube_koopman.identify import ClEdmd, ClEdmdKnownRows, ClEdmdLstsq, Delay, Trajectory, close_loop
from qube_koopman.identify.estimators.mixed import ControllerGroups, majority_controller
from qube_koopman.identify.model_selection.split import leave_one_controller_out
from qube_koopman.identify.estimators.regression import constrained_plant_solve, grouped_plant_solve
from qube_koopman.identify.estimators.stability import ClEdmdStable
from qube_koopman.identify.model_selection.sweep import SweepOptions, regularization_sweep
from qube_koopman.core.lti import DiscreteStateSpace
from linear_loops import closed_loop_trajectories, mass_spring_damper, pid_position_controller

DT = 0.01


def pd_position_controller(dt: float = DT) -> DiscreteStateSpace:
    """A PD with a filtered derivative on the position error (1 state), backward Euler."""
    import control

    from qube_koopman.core.controller import discretize_channels

    s = control.tf("s")
    return discretize_channels([8 + 3 * s * 30 / (s + 30)], dt, "backward-euler")


def static_feedback(kp: float, kd: float, dt: float = DT) -> DiscreteStateSpace:
    """``u = kp (r1 - x1) + kd (r2 - x2)``: no controller state."""
    return DiscreteStateSpace(np.zeros((0, 0)), np.zeros((0, 2)), np.zeros((1, 0)), np.array([[kp, kd]]), dt)


@pytest.fixture(scope="module")
def mixed():
    """Noise-free episodes of one plant under a PID (2 states) and a PD (1 state)."""
    A_p, B_p = mass_spring_damper()
    pid, pd = pid_position_controller(), pd_position_controller()
    a = closed_loop_trajectories(A_p, B_p, pid, measured=[0], n_episodes=3, seed=3)
    b = closed_loop_trajectories(A_p, B_p, pd, measured=[0], n_episodes=2, seed=4)
    return A_p, B_p, pid, pd, a + b, [pid] * len(a) + [pd] * len(b)


@pytest.fixture(scope="module")
def noisy_mixed():
    """The same loops with process noise: the fit is no longer exact, so its penalty matters."""
    A_p, B_p = mass_spring_damper()
    pid, pd = pid_position_controller(), pd_position_controller()
    a = closed_loop_trajectories(A_p, B_p, pid, measured=[0], n_episodes=3, seed=5, process_noise=1e-3)
    b = closed_loop_trajectories(A_p, B_p, pd, measured=[0], n_episodes=2, n=300, seed=6, process_noise=1e-3)
    return pid, pd, a + b, [pid] * len(a) + [pd] * len(b)


@pytest.mark.parametrize("regularize", ["closed_loop", "plant"])
def test_mixed_fit_recovers_the_plant(mixed, regularize):
    A_p, B_p, pid, pd, trajs, controllers = mixed
    model = ClEdmd(pid, measured=[0], regularize=regularize).fit(trajs, controllers)
    np.testing.assert_allclose(model.plant_model_.A, A_p, atol=1e-8)
    np.testing.assert_allclose(model.plant_model_.B, B_p, atol=1e-8)
    assert len(model.training_controllers_) == 2


@pytest.mark.parametrize("reference", ["pid", "pd"])
def test_mixed_fit_closed_loop_is_the_reference_controllers(mixed, reference):
    """The closed loop is self.controller's, whichever of the two it is; it predicts that loop's episodes."""
    A_p, B_p, pid, pd, trajs, controllers = mixed
    ctrl = pid if reference == "pid" else pd
    model = ClEdmd(ctrl, measured=[0]).fit(trajs, controllers)
    assert model.closed_loop_model_.n_passthrough == ctrl.n_states
    from qube_koopman.identify import closed_loop_matrices, output_selection

    A_f, B_f = closed_loop_matrices(A_p, B_p, ctrl, output_selection(2, [0]), 1)
    np.testing.assert_allclose(model.koopman_matrix_, np.hstack([A_f, B_f]), atol=1e-8)
    own = next(t for t, c in zip(trajs, controllers) if c is ctrl)
    np.testing.assert_allclose(model.predict(own), own.x, atol=1e-8)


def _explicit_plant_solve(trajs, controllers, measured, alpha, regularize):
    """The stacked problem written out from the raw episodes: its own u, S_g and penalty rows.

    u = C^c x^c + D^c (r - x_measured) + f per sample; the regressor [x_k; u_k] and the
    target x_{k+1} of every episode stacked; penalty rows sqrt(alpha w_g) S_g^T for the
    closed-loop penalty (S_g written from the controller's matrices), sqrt(alpha) I for the
    plant one; one numpy lstsq.
    """
    n_x = trajs[0].x.shape[1]
    C_p = np.eye(n_x)[measured]
    rows, targets, counts = [], [], {}
    for t, c in zip(trajs, controllers):
        u = t.xc @ c.C.T + (t.r - t.x @ C_p.T) @ c.D.T + t.f
        rows.append(np.hstack([t.x, u])[:-1])
        targets.append(t.x[1:])
        counts[id(c)] = counts.get(id(c), 0) + len(t.x) - 1
    Z, X = np.vstack(rows), np.vstack(targets)
    q = sum(counts.values())
    if regularize == "plant":
        penalty = np.sqrt(alpha) * np.eye(Z.shape[1])
    else:
        blocks = []
        for c in {id(c): c for c in controllers}.values():
            n_c, n_r, n_f = c.n_states, C_p.shape[0], c.n_outputs
            S = np.block(
                [[np.zeros((n_x, n_c)), np.eye(n_x), np.zeros((n_x, n_r + n_f))], [c.C, -c.D @ C_p, c.D, np.eye(n_f)]]
            )
            blocks.append(np.sqrt(alpha * counts[id(c)] / q) * S.T)
        penalty = np.vstack(blocks)
    A = np.vstack([Z, penalty])
    Y = np.vstack([X, np.zeros((penalty.shape[0], n_x))])
    return np.linalg.lstsq(A, Y, rcond=None)[0].T


@pytest.mark.parametrize("regularize", ["closed_loop", "plant"])
@pytest.mark.parametrize("alpha", [0.0, 0.3, 30.0])
def test_mixed_fit_equals_the_explicit_stacked_least_squares(noisy_mixed, regularize, alpha):
    pid, pd, trajs, controllers = noisy_mixed
    model = ClEdmd(pid, measured=[0], alpha=alpha, regularize=regularize).fit(trajs, controllers)
    expected = _explicit_plant_solve(trajs, controllers, [0], alpha, regularize)
    got = model.plant_koopman_matrix_
    assert np.linalg.norm(got - expected) <= 1e-8 * np.linalg.norm(expected)
    if alpha:  # the penalty is not negligible: the regularized plant is not the unregularized one
        unregularized = _explicit_plant_solve(trajs, controllers, [0], 0.0, regularize)
        assert np.linalg.norm(unregularized - expected) > 1e-4 * np.linalg.norm(expected)


def test_one_controller_through_the_new_path_is_todays_fit(noisy_mixed):
    pid, _, trajs, controllers = noisy_mixed
    mine = [t for t, c in zip(trajs, controllers) if c is pid]
    today = ClEdmd(pid, measured=[0], alpha=0.3).fit(mine)
    same = copy.deepcopy(pid)  # an equal controller, another object
    for given in ([pid] * len(mine), [same] * len(mine)):
        new = ClEdmd(pid, measured=[0], alpha=0.3).fit(mine, given)
        np.testing.assert_array_equal(new.koopman_matrix_, today.koopman_matrix_)
        np.testing.assert_array_equal(new.plant_koopman_matrix_, today.plant_koopman_matrix_)


@pytest.mark.parametrize("regularize", ["closed_loop", "plant"])
def test_grouped_solve_of_one_group_is_the_single_solve_bit_for_bit(noisy_mixed, regularize):
    pid, _, trajs, controllers = noisy_mixed
    mine = [t for t, c in zip(trajs, controllers) if c is pid]
    est = ClEdmd(pid, measured=[0])
    setup = est.setup_fit(mine)
    parts = [est.episode_snapshots(setup, t) for t in mine]
    single = est.total_statistics(setup, parts)
    grouped = ControllerGroups.of([pid] * len(mine), setup.output_matrix, setup.n_feedforward).statistics(parts)
    for alpha in (0.0, 1e-3, 10.0):
        np.testing.assert_array_equal(
            grouped_plant_solve(grouped, alpha, regularize),
            constrained_plant_solve(single, setup.plant_input_map, alpha, slice(pid.n_states, None), regularize),
        )


def test_fit_without_the_reference_controllers_episodes(noisy_mixed):
    """All episodes under the PD, closed loop asked for the PID: the PD's plant, wrapped with the PID."""
    pid, pd, trajs, controllers = noisy_mixed
    theirs = [t for t, c in zip(trajs, controllers) if c is pd]
    plant_only = ClEdmd(pd, measured=[0], alpha=0.3).fit(theirs)
    model = ClEdmd(pid, measured=[0], alpha=0.3).fit(theirs, [pd] * len(theirs))
    np.testing.assert_allclose(model.plant_koopman_matrix_, plant_only.plant_koopman_matrix_, rtol=1e-12, atol=1e-14)
    wrapped = close_loop(model.plant_model_, pid, [0])
    np.testing.assert_allclose(model.closed_loop_model_.A, wrapped.A, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(model.closed_loop_model_.B, wrapped.B, rtol=1e-12, atol=1e-14)


def _static_loop_episodes(A_p, B_p, controller, n_episodes, n, seed):
    """Noise-free episodes from random initial states, no reference, no feedforward."""
    rng = np.random.default_rng(seed)
    out = []
    K = controller.D
    for i in range(n_episodes):
        x = np.zeros((n, 2))
        x[0] = rng.normal(size=2)
        for k in range(n - 1):
            x[k + 1] = A_p @ x[k] + B_p @ (-K @ x[k])
        out.append(
            Trajectory(
                x=x,
                u=-x @ K.T,
                r=np.zeros((n, 2)),
                f=np.zeros((n, 1)),
                xc=np.zeros((n, 0)),
                name=f"static{seed}-{i}",
                dt=controller.dt,
            )
        )
    return out


def test_two_controllers_identify_a_plant_that_one_cannot():
    """Static state feedback u = -K x: one controller's data cannot tell A^p from B^p (u is a
    combination of x), two controllers' can: the classic identifiability argument of closed-loop
    identification."""
    A_p, B_p = mass_spring_damper()
    k1, k2 = static_feedback(3.0, 1.0), static_feedback(8.0, 0.5)
    a = _static_loop_episodes(A_p, B_p, k1, 3, 200, seed=1)
    b = _static_loop_episodes(A_p, B_p, k2, 3, 200, seed=2)
    truth = np.hstack([A_p, B_p])
    alone = ClEdmd(k1, measured=[0, 1]).fit(a).plant_koopman_matrix_
    both = ClEdmd(k1, measured=[0, 1]).fit(a + b, [k1] * 3 + [k2] * 3).plant_koopman_matrix_
    assert np.linalg.norm(alone - truth) > 1e-3  # the minimum-norm solution of a singular problem
    np.testing.assert_allclose(both, truth, atol=1e-8)


def test_leave_one_controller_out_sweep_scores_the_held_out_loops(mixed):
    """Each fold fits the plant to one controller's episodes and predicts the other's loop: exact data,
    so R^2 is 1 at a small alpha; the fold models are the held-out controller's closed loops."""
    A_p, B_p, pid, pd, trajs, controllers = mixed
    splits = leave_one_controller_out(ControllerGroups.of(controllers, np.eye(2)[[0]], 1).labels)
    assert [v.tolist() for _, v in splits] == [[0, 1, 2], [3, 4]]
    sweep = regularization_sweep(
        ClEdmd(pid, measured=[0]),
        trajs,
        [1e-10, 1e2],
        splits,
        scorings=("cl", "plant"),
        controllers=controllers,
        options=SweepOptions(keep_fold_models=True),
    )
    np.testing.assert_allclose(sweep.cv_r2["cl"][:, 0], 1.0, atol=1e-8)
    np.testing.assert_allclose(sweep.cv_r2["plant"][:, 0], 1.0, atol=1e-8)
    assert sweep.cv_r2["cl"][:, 1].max() < 0.999  # a heavy penalty does not fit: the scores are real
    held_out = [closed[0].n_passthrough for closed, _, _ in sweep.fold_models]
    assert held_out == [pid.n_states, pd.n_states]
    assert sweep.closed_loop_models[0].n_passthrough == pid.n_states  # the final fit: the estimator's loop


def test_sweep_refuses_a_fold_that_validates_two_controllers(mixed):
    *_, pid, pd, trajs, controllers = mixed
    splits = [(np.array([0, 1, 4]), np.array([2, 3]))]
    with pytest.raises(ValueError, match="fold 1's validation episodes were recorded under 2 controllers"):
        regularization_sweep(ClEdmd(pid, measured=[0]), trajs, [1e-3], splits, controllers=controllers)


def test_majority_controller(mixed):
    *_, pid, pd, trajs, controllers = mixed
    assert majority_controller(controllers) is pid
    assert majority_controller([pd, pid, copy.deepcopy(pd), pid]) is pd  # a tie: the first to appear


def test_bad_controller_lists_are_refused(mixed):
    *_, pid, pd, trajs, controllers = mixed
    with pytest.raises(ValueError, match="4 controllers for 5 episodes"):
        ClEdmd(pid, measured=[0]).fit(trajs, controllers[:4])
    with pytest.raises(
        ValueError, match="episode ep0: the controller has 1 states but the data's controller state has 2 channels"
    ):
        ClEdmd(pid, measured=[0]).fit(trajs, [pd] + controllers[1:])
    with pytest.raises(ValueError, match="must be a DiscreteStateSpace"):
        ClEdmd(pid, measured=[0]).fit(trajs, ["pid"] + controllers[1:])
    from dataclasses import replace

    with pytest.raises(ValueError, match="episode ep1: closed-loop data need the controller state 'xc'"):
        ClEdmd(pid, measured=[0]).fit([trajs[0], replace(trajs[1], xc=None)] + trajs[2:], controllers)
    with pytest.raises(ValueError, match="leave-one-controller-out needs episodes of at least two"):
        leave_one_controller_out([0, 0, 0])


@pytest.mark.parametrize("cls", [ClEdmdLstsq, ClEdmdStable])
def test_single_loop_estimators_refuse_mixed_controllers(mixed, cls):
    *_, pid, pd, trajs, controllers = mixed
    with pytest.raises(ValueError, match=f"{cls.__name__} fits episodes of one controller"):
        cls(pid, measured=[0]).fit(trajs, controllers)


def test_known_rows_variant_fits_the_same_plant(noisy_mixed):
    pid, pd, trajs, controllers = noisy_mixed
    free = ClEdmd(pid, measured=[0], alpha=0.3).fit(trajs, controllers)
    known = ClEdmdKnownRows(pid, measured=[0], alpha=0.3).fit(trajs, controllers)
    np.testing.assert_array_equal(free.plant_koopman_matrix_, known.plant_koopman_matrix_)
    wrapped = close_loop(known.plant_model_, pid, [0])
    np.testing.assert_allclose(known.closed_loop_model_.A, wrapped.A, rtol=1e-12, atol=1e-14)


def test_partial_fold_fits_score_as_full_ones(mixed):
    """A search's folds fit only the rows re-lifted predictions use, counted per episode's own controller
    states (2 for the PID, 1 for the PD): the scores are those of the full fits."""
    A_p, B_p, pid, pd, trajs, controllers = mixed
    splits = leave_one_controller_out([0, 0, 0, 1, 1])
    alphas = [1e-6, 1e-1, 1e1]
    est = ClEdmd(pid, lifting=[Delay(2)], measured=[0])  # 6 lifted states, 2 of them fitted in the folds
    full = regularization_sweep(est, trajs, alphas, splits, controllers=controllers)
    partial = regularization_sweep(
        est, trajs, alphas, splits, controllers=controllers, options=SweepOptions(fit_all=False, keep_fold_models=True)
    )
    for closed, _, _ in partial.fold_models:
        n_c = closed[0].n_passthrough
        assert np.isnan(closed[0].A[n_c + 2 :]).all() and np.isfinite(closed[0].A[: n_c + 2]).all()
    np.testing.assert_allclose(partial.cv_r2["cl"], full.cv_r2["cl"], rtol=1e-10)
    np.testing.assert_allclose(partial.cv_r2["plant"], full.cv_r2["plant"], rtol=1e-10)
