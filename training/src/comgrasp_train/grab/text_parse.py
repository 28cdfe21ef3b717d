"""The inverse of ``text.describe``: a prompt's intent, named hand(s) and object.

Accepts every template of ``text.TEMPLATES`` with either article, every intent phrase of
``text.INTENT_PHRASES`` (GRAB's and SynthGrasp's), with or without the hand phrase
(" with his left hand", " with both hands", " from her right hand to her left"), plus a
few natural variants ("two hands", "using the left hand", "in their right hand").
Anything else parses to :data:`UNKNOWN`, never an exception.
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass

from ..objects.catalogue import CATALOGUE
from .text import GRAB_NOUNS, INTENT_PHRASES, PERSON, object_noun

SIDES: tuple[str, str] = ("left", "right")


@dataclass(frozen=True)
class Intent:
    """What a prompt asks for; ``intent`` is None when the text matches no template."""

    intent: str | None
    hands: str | None = None  # 'left' | 'right' | 'both' | 'left>right' | 'right>left' (pass: giver>taker)
    object: str | None = None  # catalogue / GRAB name when known, else the noun as written

    @property
    def known(self) -> bool:
        return self.intent is not None

    @property
    def sides(self) -> tuple[str, ...]:
        """The hands named, in order (the giver first for a pass)."""
        if self.hands is None:
            return ()
        return tuple(self.hands.split(">")) if ">" in self.hands else SIDES if self.hands == "both" else (self.hands,)


UNKNOWN = Intent(None)

_POSS = r"(?:his|her|their|the)"
_HAND_PHRASES = (  # (pattern ending the sentence, hands from its match)
    (re.compile(rf"\s+from\s+{_POSS}\s+(left|right)(?:\s+hand)?\s+to\s+{_POSS}\s+(left|right)(?:\s+hand)?$"),
     lambda m: f"{m[1]}>{m[2]}" if m[1] != m[2] else None),
    (re.compile(rf"\s+(?:with|using)\s+(?:both|two)\s+(?:of\s+{_POSS}\s+)?hands$"), lambda m: "both"),
    (re.compile(rf"\s+(?:with|using|in)\s+{_POSS}\s+(left|right)\s+hand$"), lambda m: m[1]),
)
_SUBJECT = re.compile(rf"^(?:a|an|the)\s+(?:{'|'.join(sorted({p for p, _ in PERSON.values()} | {'person'}))})"
                      r"\s+(?:is\s+)?(.+)$")


def _phrase_regex(phrase: str) -> re.Pattern:
    head, tail = phrase.split("{obj}")
    return re.compile("^" + re.escape(head) + r"(?P<obj>.+?)" + re.escape(tail) + "$")


# Both verb forms of every intent, longest first so that none shadows a longer one.
_VERBS = sorted(((intent, _phrase_regex(p)) for intent, ps in INTENT_PHRASES.items() for p in ps),
                key=lambda x: -len(x[1].pattern))


def _noun_table() -> dict[str, str]:
    """Noun -> object name: every default noun, and the aliases naming one object only
    ("cube" names three)."""
    table = {object_noun(n): n for n in CATALOGUE} | {noun: n for n, noun in GRAB_NOUNS.items()}
    count = Counter(a for spec in CATALOGUE.values() for a in spec.aliases)
    for name, spec in CATALOGUE.items():
        for a in spec.aliases:
            if count[a] == 1:
                table.setdefault(a, name)
    return table


_NOUNS = _noun_table()


def parse_prompt(text: str) -> Intent:
    """Intent, hand(s) and object of a prompt; :data:`UNKNOWN` when no template matches."""
    if not isinstance(text, str):
        return UNKNOWN
    m = _SUBJECT.match(" ".join(text.lower().strip().rstrip(".!").split()))
    if not m:
        return UNKNOWN
    rest, hands = m[1], None
    for pattern, pick in _HAND_PHRASES:
        h = pattern.search(rest)
        if h:
            rest, hands = rest[: h.start()], pick(h)
            break
    for intent, verb in _VERBS:
        v = verb.match(rest)
        if v:
            noun = re.sub(r"^(?:the|an|a)\s+", "", v["obj"])
            return Intent(intent, hands, _NOUNS.get(noun, noun))
    return UNKNOWN
