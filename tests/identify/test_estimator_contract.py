"""scikit-learn's estimator contract, for every estimator and every lifting the package exports.

Constructor arguments are stored unchanged under their own names (checked by ``fit``, never by
``__init__``); ``get_params(deep=True)`` lists nested parameters as ``lifting__steps`` and
round-trips through ``set_params``; ``clone`` builds an equal, unfitted copy; ``fit`` returns self
and sets only attributes ending in ``_`` that did not exist before. scikit-learn itself is not a
dependency (nor installed), so ``sklearn.base.clone`` is not tried here.
"""

from __future__ import annotations

import copy
import dataclasses
import inspect

import numpy as np
import pytest
from _public_api import all_modules
from linear_loops import (
    closed_loop_trajectories,
    mass_spring_damper,
    pid_position_controller,
)
from qube_koopman import identify
from qube_koopman.identify import (
    Arx,
    ClArx,
    ClEdmd,
    ClEdmdKnownRows,
    ClEdmdLstsq,
    ClEdmdSdp,
    ClEdmdStable,
    Constant,
    CoulombFriction,
    Delay,
    Edmd,
    GaussianRbf,
    Lifting,
    LiftingFunction,
    Polynomial,
    ThinPlateRbf,
    Trajectory,
    Trigonometric,
    clone,
)
from qube_koopman.identify.params import Params

CONTROLLER = pid_position_controller()


def _unusual(cls) -> dict:
    """Legal but unusual constructor arguments (numpy scalars, lists for tuples, arrays): stored as
    given, they must come back as the same objects."""
    closed = {
        "controller": CONTROLLER,
        "lifting": (Polynomial(np.int64(2)), Delay(np.int64(2))),
        "alpha": np.float64(1e-3),
        "measured": np.array([0]),
    }
    return {
        Edmd: {
            "lifting": Lifting([Delay(np.int64(2))]),
            "alpha": np.float32(0.25),
            "input_lifting": Lifting([Polynomial(np.int64(1))]),
        },
        ClEdmd: {**closed, "regularize": "plant", "known_controller_rows": np.bool_(False)},
        ClEdmdKnownRows: {**closed, "regularize": "closed_loop", "known_controller_rows": True},
        ClEdmdLstsq: {**closed, "lifting": [Delay(1)]},
        ClEdmdSdp: {
            **closed,
            "lifting": [Delay(1)],
            "regularize": "plant",
            "solver": "clarabel",
            "solver_options": {"max_iter": 300},
        },
        ClEdmdStable: {
            **closed,
            "max_radius": np.float64(0.999),
            "center": 0,
            "n_iter": np.int64(1),
            "solver": "CLARABEL",
            "method": "sqp",
        },
        Arx: {"output_lags": np.int64(2), "input_lags": 2, "inputs": ["u"], "alpha": np.float32(0.0)},
        ClArx: {"controller": CONTROLLER, "output_lags": np.int64(4), "input_lags": 4, "alpha": 0},
        Lifting: {"steps": [Polynomial(2), Delay(np.int64(1))]},
        Constant: {},
        Polynomial: {"order": np.int64(3)},
        Delay: {"n_delays": np.int64(3)},
        ThinPlateRbf: {
            "n_centers": np.int64(4),
            "shape": 2,
            "offset": np.float32(0.01),
            "centers": None,
            "seed": np.int64(7),
        },
        GaussianRbf: {
            "n_centers": 2,
            "shape": np.float64(0.5),
            "centers": [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]],
            "seed": None,
        },
        Trigonometric: {"features": [1]},
        CoulombFriction: {"feature": np.int64(0), "lag": np.int64(2), "width": 1},
    }[cls]


ESTIMATORS = [Edmd, ClEdmd, ClEdmdKnownRows, ClEdmdLstsq, ClEdmdSdp, ClEdmdStable, Arx, ClArx]
LIFTINGS = [Lifting, Constant, Polynomial, Delay, ThinPlateRbf, GaussianRbf, Trigonometric, CoulombFriction]
# The bases the classes above share: not constructed by users.
BASES = {"Estimator", "SnapshotEstimator", "ClosedLoopKoopman", "LiftingFunction", "RadialBasis", "Params"}


def same(a, b) -> bool:
    """Equal parameter values: estimators by class and parameters, arrays by dtype and entries,
    containers item by item (of the same type), dataclasses (a controller) field by field."""
    if hasattr(a, "get_params") and not isinstance(a, type):
        return type(a) is type(b) and same(a.get_params(deep=False), b.get_params(deep=False))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return type(a) is type(b) and a.dtype == b.dtype and np.array_equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return type(a) is type(b) and all(same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    return type(a) is type(b) and bool(a == b)


def test_every_exported_estimator_and_lifting_is_covered():
    """The lists above are what the package defines: a new estimator or lifting is tested here."""
    defined = {
        obj
        for module in all_modules(private=True)
        if module.__name__.startswith(identify.__name__)
        for obj in vars(module).values()
        if inspect.isclass(obj)
        and issubclass(obj, Params)
        and obj.__module__ == module.__name__
        and obj.__name__ not in BASES
    }
    assert defined == set(ESTIMATORS + LIFTINGS)
    assert {cls.__name__ for cls in defined} <= set(identify.__all__)


@pytest.mark.parametrize("cls", ESTIMATORS + LIFTINGS, ids=lambda cls: cls.__name__)
def test_the_constructor_stores_its_arguments_unchanged(cls):
    args = _unusual(cls)
    assert set(args) == set(inspect.signature(cls).parameters)  # every parameter is tried
    est = cls(**args)
    for name, value in args.items():
        assert getattr(est, name) is value, name
    assert est.get_params(deep=False).keys() == args.keys()
    assert all(est.get_params(deep=False)[name] is value for name, value in args.items())
    # the defaults too: a parameter always readable under its own name
    default = cls(controller=CONTROLLER) if "controller" in args else cls()
    assert default.get_params(deep=False).keys() == args.keys()


@pytest.mark.parametrize("cls", ESTIMATORS + LIFTINGS, ids=lambda cls: cls.__name__)
def test_clone_is_an_equal_unfitted_copy_of_new_objects(cls):
    est = cls(**_unusual(cls))
    new = clone(est)
    assert type(new) is cls and new is not est
    assert same(new.get_params(), est.get_params())
    assert same(new.get_params(deep=False), est.get_params(deep=False))
    for name, value in est.get_params(deep=False).items():
        # parameters are copied (a lifting's steps cloned, a controller deep-copied), never shared;
        # immutable values (a number, a string) are their own deep copy
        if copy.deepcopy(value) is not value:
            assert new.get_params(deep=False)[name] is not value, name
    assert not [name for name in vars(new) if name.endswith("_")]


@pytest.mark.parametrize("cls", ESTIMATORS + LIFTINGS, ids=lambda cls: cls.__name__)
def test_deep_parameters_round_trip_through_set_params(cls):
    est = cls(**_unusual(cls))
    params = est.get_params(deep=True)
    nested = {key for key in params if "__" in key}
    # a parameter with parameters of its own (a Lifting) lists them as name__inner
    expected = {
        f"{name}__{inner}"
        for name, value in est.get_params(deep=False).items()
        if hasattr(value, "get_params")
        for inner in value.get_params(deep=True)
    }
    assert nested == expected
    target = cls(controller=CONTROLLER) if "controller" in params else cls()
    assert target.set_params(**params) is target
    assert same(target.get_params(deep=True), params)
    for name, value in est.get_params(deep=False).items():
        assert getattr(target, name) is value


def test_set_params_reaches_nested_parameters_and_names_unknown_ones():
    est = Edmd(lifting=Lifting([Delay(2)]), alpha=0.1)
    assert set(est.get_params()) == {"lifting", "lifting__steps", "alpha", "input_lifting"}
    steps = [Polynomial(2), Delay(5)]
    est.set_params(lifting__steps=steps, alpha=0.5)
    assert est.lifting.steps is steps and est.alpha == 0.5
    with pytest.raises(ValueError, match="unknown parameter 'lifitng' for Edmd; expected one of lifting, alpha"):
        est.set_params(lifitng__steps=[])
    with pytest.raises(ValueError, match="unknown parameter 'stpes' for Lifting; expected one of steps"):
        est.set_params(lifting__stpes=[])
    with pytest.raises(ValueError, match="parameter 'input_lifting' of Edmd is None, which has no parameters"):
        est.set_params(input_lifting__steps=[])


def test_clone_refuses_what_is_not_an_estimator_and_copies_containers():
    with pytest.raises(TypeError, match="no get_params"):
        clone(CONTROLLER)
    assert same(clone(CONTROLLER, safe=False), CONTROLLER)
    steps = [Delay(2), Polynomial(3)]
    copies = clone(steps)
    assert type(copies) is list and same(copies, steps) and all(c is not s for c, s in zip(copies, steps))


def test_clone_refuses_a_constructor_that_changes_its_arguments():
    class Converting(Lifting):
        def __init__(self, steps=()) -> None:
            self.steps = list(steps)  # a new list: not the argument

    with pytest.raises(RuntimeError, match="does not store its parameter 'steps' unchanged"):
        clone(Converting([Delay(2)]))


def _closed_loop_data() -> list[Trajectory]:
    """Position-only episodes of a PID loop with feedforward: every estimator fits them."""
    A_p, B_p = mass_spring_damper()
    trajs = closed_loop_trajectories(A_p, B_p, CONTROLLER, [0], n_episodes=3, n=300, seed=3)
    return [Trajectory(x=t.x[:, :1], u=t.u, r=t.r, f=t.f, xc=t.xc, dt=t.dt) for t in trajs]


def _fit_arguments(cls, data):
    """What ``fit`` takes for this class: episodes (and names, for a lifting step)."""
    if cls in ESTIMATORS:
        return (data,)
    states = [t.x for t in data]
    if cls is Lifting:
        return (states,)
    if cls is CoulombFriction:  # it reads the delayed arm angle: give it a Delay(2)'s output
        delayed = Lifting([Delay(2)]).fit(states, ["theta"])
        return [delayed.transform(x) for x in states], delayed.feature_names_out_
    wide = [np.hstack([x, x**2, np.sin(x)]) for x in states]  # three features: the RBF centres' width
    return wide, ["a", "b", "c"]


@pytest.fixture(scope="module")
def data():
    return _closed_loop_data()


@pytest.mark.parametrize("cls", ESTIMATORS + LIFTINGS, ids=lambda cls: cls.__name__)
def test_fit_returns_self_and_learns_only_attributes_ending_in_underscore(cls, data):
    args = _unusual(cls)
    est = cls(**args)
    before = dict(vars(est))
    assert not [name for name in before if name.endswith("_")]
    assert est.fit(*_fit_arguments(cls, data)) is est
    learned = [name for name in vars(est) if name not in before]
    assert learned, "fit learned nothing"
    assert all(name.endswith("_") or name.startswith("_") for name in learned), learned
    # fit changes no parameter: the same objects, and nothing rebound
    assert all(vars(est)[name] is value for name, value in before.items())
    assert all(est.get_params(deep=False)[name] is value for name, value in args.items())
    # and a clone of the fitted object is unfitted
    assert not [name for name in vars(clone(est)) if name.endswith("_")]


@pytest.mark.parametrize(
    "make, fit_error",
    [
        (lambda: Polynomial(0), "polynomial order must be an integer >= 1, got 0"),
        (lambda: Delay(1.5), "number of delays must be an integer >= 0, got 1.5"),
        (lambda: ThinPlateRbf(shape=-1), "RBF shape must be positive, got -1"),
        (lambda: ThinPlateRbf(offset=0), "thin-plate offset must be positive, got 0"),
        (lambda: GaussianRbf(n_centers=0), "number of RBF centres must be an integer >= 1, got 0"),
        (lambda: Trigonometric([0, 0]), r"distinct non-negative feature indices, got \(0, 0\)"),
        (lambda: CoulombFriction(lag=0), "friction lag must be a positive number of samples, got 0"),
    ],
)
def test_an_estimator_with_a_bad_lifting_fails_at_fit_with_the_same_message(make, fit_error, data):
    step = make()  # constructed: nothing is checked yet
    for est in (Edmd(lifting=[step]), ClEdmd(CONTROLLER, lifting=[Delay(10), step])):
        with pytest.raises(ValueError, match=fit_error):
            est.fit(data)


def test_lifting_function_is_the_abstract_base():
    assert inspect.isabstract(LiftingFunction)


def _snapshot_estimator(cls):
    """A least-squares estimator of ``cls`` with a lifting whose fit does not depend on the episodes."""
    lifting = [Polynomial(2), Delay(2)]
    if cls is Edmd:
        return Edmd(lifting=lifting, alpha=1e-3)
    return cls(CONTROLLER, lifting=lifting, alpha=1e-3)


@pytest.mark.parametrize(
    "cls",
    [cls for cls in ESTIMATORS if issubclass(cls, identify.SnapshotEstimator) and cls is not ClEdmdSdp],
    ids=lambda cls: cls.__name__,
)
def test_the_statistics_protocol_fits_as_fit_does_and_adds_an_episode_to_refit(cls, data):
    """setup_fit, episode_snapshots folded into statistics_fold, finish_fit: ``fit`` itself; an episode
    added to the running total after a first fit refits as a fit on every episode (live identification)."""
    fitted = _snapshot_estimator(cls).fit(data)
    estimator = _snapshot_estimator(cls)
    setup = estimator.setup_fit(data[:2])
    assert isinstance(setup, identify.FitSetup)
    fold = estimator.statistics_fold(setup)
    for index, trajectory in enumerate(setup.trajectories):
        fold.add(index, estimator.episode_snapshots(setup, trajectory))
    assert estimator.finish_fit(setup, fold.total()) is estimator
    first = estimator.koopman_matrix_.copy()
    np.testing.assert_array_equal(first, _snapshot_estimator(cls).fit(data[:2]).koopman_matrix_)
    fold.add(2, estimator.episode_snapshots(setup, data[2]))
    estimator.finish_fit(setup, fold.total())
    assert not np.allclose(estimator.koopman_matrix_, first)
    np.testing.assert_allclose(estimator.koopman_matrix_, fitted.koopman_matrix_, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(_snapshot_estimator(cls).fit_setup(setup).koopman_matrix_, first)


def test_the_sdp_reference_says_it_fits_with_fit_only(data):
    """ClEdmdSdp solves on a Gram matrix its fit builds: finish_fit refuses with a message saying so."""
    estimator = _snapshot_estimator(ClEdmdSdp)
    setup = estimator.setup_fit(data)
    fold = estimator.statistics_fold(setup)
    fold.add(0, estimator.episode_snapshots(setup, data[0]))
    with pytest.raises(NotImplementedError, match="fits with fit only"):
        estimator.finish_fit(setup, fold.total())
