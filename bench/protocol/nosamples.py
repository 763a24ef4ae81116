"""Why a split has no samples under a setting, said with what ``datasets check`` knows, and the fix.

A split can be empty for three reasons, each with its own fix: the root holds no sequence of
that split but holds sequences of another (pick that split), it holds no sequence of any split
(the root is wrong), or its sequences are all shorter than the setting's window (pick a
setting with a shorter horizon, or the every-frame policy). The caller says how its user picks
a split, a setting and a policy (:class:`Options`): ``--split train`` on the command line,
``splits = ["train"]`` in an experiment file.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable

from pcfbench.errors import PcfbenchError
from pcfbench.kinds import PolicyKind
from pcfbench.protocol.samples import SampleBuilder
from pcfbench.protocol.settings import Setting

#: how many sequence names a message lists before "and N more"
MOST_NAMES = 5


@dataclass(frozen=True)
class Options:
    """How the caller's user picks a split, a setting and a policy: ``{}`` is the name (None: the
    caller offers no choice of it)."""

    split: str = "--split {}"
    setting: str | None = "--setting {}"
    policy: str | None = "--policy {}"


CLI = Options()
EXPERIMENT_FILE = Options(split='splits = ["{}"]', setting='settings = ["{}"]', policy='policy = "{}"')


@dataclass(frozen=True)
class NoSamples:
    """The cause and fix of an empty split; ``kind`` is what to change: "split", "setting" or "root"."""

    kind: str
    message: str


def window(setting: Setting, rule: PolicyKind) -> int:
    """Consecutive sweeps a sequence needs for one sample under ``rule`` (full-context: every past and
    future sweep inside it; every-frame: one)."""
    if rule == PolicyKind.FULL_CONTEXT:
        return (setting.past - 1) * setting.stride + 1 + setting.future * setting.stride
    return 1


def _names(names: list[str]) -> str:
    more = f" and {len(names) - MOST_NAMES} more" if len(names) > MOST_NAMES else ""
    return ", ".join(names[:MOST_NAMES]) + more


def no_sequences(adapter: Any, split: str, head: str, options: Options = CLI) -> NoSamples:
    """``head`` and why ``split`` of ``adapter`` has no sequence: those under the root are in other
    splits (named, with the option that picks one), or the root holds none of any split."""
    found: dict[str, list[str]] = {}
    # an embedded dataset makes a split's data when it is listed: never make one to say this
    if not getattr(type(adapter), "embedded", False):
        for other in adapter.splits():
            if other != split:
                try:
                    seqs = adapter.sequence_names(other)
                except PcfbenchError:
                    continue
                if seqs:
                    found[other] = seqs
    where = f"the root {adapter.root}"
    if not found:
        return NoSamples("root", f"{head}: {where} holds no sequence of any split of {adapter.name} "
                                 f"({', '.join(adapter.splits())}); `pcfbench datasets check {adapter.root}` "
                                 "shows what it holds")
    held = " and ".join(f"split {s} ({_names(seqs)})" for s, seqs in found.items())
    picks = " or ".join(options.split.format(s) for s in found)
    return NoSamples("split", f"{head}: {where} holds no sequence of split {split}; its sequences are in "
                              f"{held}: pick {'it' if len(found) == 1 else 'one'} with {picks}")


def explain(builder: SampleBuilder, split: str, *, settings: Iterable[Setting] = (), options: Options = CLI) -> NoSamples:
    """Why ``builder`` finds no sample in ``split`` (call it when ``sample_keys(split)`` is empty).

    ``settings``: the settings to suggest when the sequences are too short for this one (those
    of the dataset's rate whose window fits the longest sequence are named)."""
    adapter, setting, policy = builder.adapter, builder.setting, builder.sample_policy
    head = f"{adapter.name}:{split} has no samples for setting {setting.name} ({policy.name})"
    names = adapter.sequence_names(split)
    if not names:
        return no_sequences(adapter, split, head, options)
    lengths = {name: len(builder.sequence(name)) for name in names}
    longest = max(lengths.values())
    need = window(setting, policy.rule)
    longest_names = [n for n, v in lengths.items() if v == longest]
    if policy.rule == PolicyKind.FULL_CONTEXT:
        why = (f"a sample needs {need} consecutive sweeps ({setting.past} past and {setting.future} future, "
               f"{setting.stride} apart) and the longest of its {len(names)} sequence(s) has {longest} "
               f"({_names(longest_names)})")
    else:
        why = f"its {len(names)} sequence(s) ({_names(names)}) have no sweeps"
    fixes = []
    fitting = [s for s in settings
               if s.name != setting.name and abs(s.rate_hz - adapter.rate_hz) <= 1e-6 and window(s, policy.rule) <= longest]
    if fitting and options.setting is not None:
        fixes.append("a setting of a shorter horizon: " + " or ".join(
            f"{options.setting.format(s.name)} (needs {window(s, policy.rule)})" for s in fitting))
    every_frame = [p.name for p in builder.protocol.policies.values() if p.kind == PolicyKind.EVERY_FRAME]
    if policy.rule == PolicyKind.FULL_CONTEXT and longest > 0 and every_frame and options.policy is not None:
        fixes.append(f"{options.policy.format(every_frame[0])} (every sweep a sample; sweeps outside the sequence "
                     "are empty)")
    fix = f"; pick {', or '.join(fixes)}" if fixes else "; longer sequences are needed"
    return NoSamples("setting", f"{head}: {why}{fix}")
