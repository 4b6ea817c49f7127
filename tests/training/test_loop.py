"""The training loop's contract with the trainer is typed (``loop.LoopTrainer``) and complete."""

from __future__ import annotations

import inspect
import re
import typing

from sagrasp_jax.training import loop
from sagrasp_jax.training.trainer import Trainer


def _protocol_members() -> set[str]:
    names = set(typing.get_type_hints(loop.LoopTrainer))
    names |= {n for n, v in vars(loop.LoopTrainer).items() if not n.startswith("_") and (callable(v) or isinstance(v, property))}
    return names


def test_the_loop_uses_only_what_its_protocol_declares():
    used = set(re.findall(r"\btr\.(\w+)", inspect.getsource(loop.train)))
    assert used, "the loop reads nothing of the trainer?"
    assert used - _protocol_members() == set(), "loop.train uses trainer members LoopTrainer does not declare"
    assert {"run_calls", "end_cycles", "hosts", "compile"} <= used


def test_the_trainer_has_every_member_the_protocol_declares():
    annotated = set(typing.get_type_hints(loop.LoopTrainer))
    init = inspect.getsource(Trainer.__init__)
    for name in sorted(_protocol_members()):
        on_class = hasattr(Trainer, name)
        set_in_init = re.search(rf"self\.{name}\b[^=\n]*=|\bself\.(\w+, )*{name}(, \w+)* =", init) is not None
        assert on_class or (name in annotated and set_in_init), f"Trainer lacks LoopTrainer.{name}"
    for name in ("compile", "run_calls", "cycle_due", "end_cycles", "save_checkpoint", "export_finished", "summary"):
        declared = inspect.signature(getattr(loop.LoopTrainer, name))
        actual = inspect.signature(getattr(Trainer, name))
        assert list(declared.parameters) == list(actual.parameters), name
