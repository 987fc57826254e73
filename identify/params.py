"""The parameter contract of scikit-learn without scikit-learn: get_params, set_params, clone.

As ``sklearn.base.BaseEstimator``: an object's parameters are its constructor's arguments, stored
unchanged under their own names (checked by ``fit``, never by ``__init__``); ``get_params(deep=True)``
also lists the parameters of parameters that have some, as ``lifting__steps``; ``set_params`` takes
the same keys; :func:`clone` builds a new unfitted object from deep copies of the parameters.
Estimators (``identify.estimators.base.Estimator``), liftings and lifting functions share it.
"""

from __future__ import annotations

import copy
import inspect
from typing import Any

__all__ = ["Params", "clone"]


class Params:
    """Parameters of an object: the arguments of its constructor, stored unchanged.

    ``get_params``, ``set_params`` and a ``repr`` showing them, as scikit-learn's estimators have.
    """

    @classmethod
    def _param_names(cls) -> list[str]:
        """The constructor's argument names, in its order (none when the class has no constructor)."""
        if cls.__init__ is object.__init__:
            return []
        names = []
        for name, parameter in inspect.signature(cls.__init__).parameters.items():
            if name == "self" or parameter.kind is inspect.Parameter.VAR_KEYWORD:
                continue
            if parameter.kind is inspect.Parameter.VAR_POSITIONAL:
                raise TypeError(f"{cls.__name__}'s constructor takes *{name}: its parameters must be named")
            names.append(name)
        return names

    def get_params(self, deep: bool = True) -> dict:
        """The constructor's arguments, as stored.

        Parameters
        ----------
        deep : bool
            Also list the parameters of every parameter that has some (a lifting's steps,
            ``lifting__steps``), as scikit-learn does for nested estimators.

        Returns
        -------
        dict
            Parameter name to value.
        """
        out: dict[str, Any] = {}
        for name in self._param_names():
            value = getattr(self, name)
            if deep and hasattr(value, "get_params") and not isinstance(value, type):
                out.update((f"{name}__{key}", inner) for key, inner in value.get_params().items())
            out[name] = value
        return out

    def set_params(self, **params) -> Params:
        """Set parameters, nested ones as ``lifting__steps`` (unknown names are an error).

        Parameters
        ----------
        **params
            Parameter name to new value; ``name__inner`` sets the parameter ``inner`` of the
            parameter ``name``.

        Returns
        -------
        self
        """
        valid = self._param_names()
        nested: dict[str, dict] = {}
        for key, value in params.items():
            name, nest, inner = key.partition("__")
            if name not in valid:
                raise ValueError(
                    f"unknown parameter {name!r} for {type(self).__name__}; expected one of {', '.join(valid)}"
                )
            if nest:
                nested.setdefault(name, {})[inner] = value
            else:
                setattr(self, name, value)
        for name, values in nested.items():
            owner = getattr(self, name)
            if not hasattr(owner, "set_params"):
                raise ValueError(
                    f"parameter {name!r} of {type(self).__name__} is {owner!r}, which has no "
                    f"parameters to set ({', '.join(f'{name}__{key}' for key in values)})"
                )
            owner.set_params(**values)
        return self

    def __repr__(self) -> str:
        params = ", ".join(f"{k}={v!r}" for k, v in self.get_params(deep=False).items())
        return f"{type(self).__name__}({params})"


def clone(estimator, *, safe: bool = True):
    """A new unfitted estimator with the same parameters, as ``sklearn.base.clone``.

    Parameters
    ----------
    estimator : estimator, lifting, or list, tuple or set of them
        What to copy. Its parameters (``get_params(deep=False)``) are cloned in turn: an
        estimator or lifting among them is cloned, anything else (a controller, an array) is
        deep-copied. Fitted attributes are not copied.
    safe : bool
        Refuse an object without ``get_params`` (a TypeError); when false it is deep-copied.

    Returns
    -------
    object
        The new object, of the same class, constructed from the cloned parameters.

    Raises
    ------
    TypeError
        ``safe`` and an object without ``get_params``.
    RuntimeError
        A constructor that does not store a parameter unchanged under its own name.

    Examples
    --------
    >>> from qube_koopman.identify import Delay, Edmd, clone
    >>> estimator = Edmd(lifting=[Delay(3)], alpha=0.1)
    >>> copy = clone(estimator)
    >>> copy
    Edmd(lifting=[Delay(n_delays=3)], alpha=0.1, input_lifting=None)
    >>> copy.lifting[0] is estimator.lifting[0]
    False
    """
    if isinstance(estimator, (list, tuple, set, frozenset)):
        return type(estimator)([clone(item, safe=safe) for item in estimator])
    if not hasattr(estimator, "get_params") or isinstance(estimator, type):
        if not safe:
            return copy.deepcopy(estimator)
        raise TypeError(f"cannot clone {estimator!r} ({type(estimator).__name__}): it has no get_params method")
    params = {name: clone(value, safe=False) for name, value in estimator.get_params(deep=False).items()}
    new = type(estimator)(**params)
    stored = new.get_params(deep=False)
    for name, value in params.items():
        if stored[name] is not value:
            raise RuntimeError(
                f"cannot clone {estimator!r}: {type(estimator).__name__}'s constructor does not "
                f"store its parameter {name!r} unchanged"
            )
    return new
