"""stages/window_model.py: the Protocols of adapt's window model, held to the classes that implement them
(every member present; every method takes the Protocol's positional parameters, its own extras defaulted)."""
from __future__ import annotations

import dis
import inspect

import pytest

from stages import observations, window_backends, windows
from stages.window_model import Observation, Window, WindowBackend


def _members(protocol: type) -> list[str]:
    names = set(getattr(protocol, "__annotations__", {}))
    names |= {n for n, v in vars(protocol).items()
              if not n.startswith("_") and (callable(v) or isinstance(v, property))}
    return sorted(names)


def _instance_attributes(cls: type) -> set[str]:
    """Attributes its __init__ assigns (``self.NAME = …``: the STORE_ATTR instructions of the compiled code, so
    that the check does not depend on the source file as it is now)."""
    init = vars(cls).get("__init__")
    if init is None:
        return set()
    return {i.argval for i in dis.get_instructions(init) if i.opname == "STORE_ATTR"}


def missing_members(cls: type, protocol: type) -> list[str]:
    """The members of ``protocol`` that ``cls`` lacks, or whose positional parameters its method cannot take."""
    out = []
    for name in _members(protocol):
        if not hasattr(cls, name) and name not in _instance_attributes(cls):
            out.append(name)
            continue
        want = vars(protocol).get(name)
        have = inspect.getattr_static(cls, name, None)
        if not callable(want) or not callable(have):
            continue
        p_want = list(inspect.signature(want).parameters.values())[1:]
        p_have = list(inspect.signature(have).parameters.values())
        p_have = p_have if isinstance(have, staticmethod) else p_have[1:]
        if any(p.kind is p.VAR_POSITIONAL for p in p_have):
            continue
        positional = [p for p in p_have if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
        required = [p for p in positional if p.default is p.empty]
        if len(positional) < len(p_want) or len(required) > len(p_want):
            out.append(f"{name}{inspect.signature(have)}")
    return out


@pytest.mark.parametrize("cls, protocol", [
    (window_backends.FullSpace, WindowBackend), (window_backends.ReducedSpace, WindowBackend),
    (windows.StartWindow, Window), (windows.StaticWindow, Window),
    (observations.MarkerObservation, Observation), (observations.VisionObservation, Observation),
], ids=lambda x: x.__name__)
def test_adapt_classes_follow_the_protocols(cls, protocol):
    assert missing_members(cls, protocol) == []


def test_the_check_sees_a_missing_member_and_a_wrong_signature():
    class Half:
        kind = "x"
        huber = None
        noise_floor = 0.0

        def available(self):
            return 0

        def loss(self, frames):  # one positional parameter short
            return None

    missing = missing_members(Half, Observation)
    assert "rebind" in missing and "residuals" in missing and any(m.startswith("loss(") for m in missing)
    assert "available" not in missing and "kind" not in missing
