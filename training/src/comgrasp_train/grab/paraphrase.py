"""Many ways to ask for the same grasp: the training texts beyond the paper's templates,
and a held-out set of phrasings the model never sees in training.

A prompt is built from parts, each drawn from a list:

* who: "A man", "The woman", "Someone", "A person", ... or nobody (an imperative:
  "Pick up the mug with the left hand", as a game developer writes it);
* the verb phrase of the intent in three forms (third person, -ing, imperative), with
  synonyms ("picks up", "raises", "takes a sip from", "examines", "transfers", "offers");
* the object by any of its catalogue aliases ("ball", "block", "ring"), with "the" or "a";
* the hand(s), in several wordings ("with his left hand", "using the left hand",
  "left-handed", "with both hands", "from her right hand to her left");
* casing and the final full stop.

``HELD_OUT`` holds verb phrases, subjects and hand wordings that no training text uses;
``paraphrases(..., held_out=True)`` draws only from those (with the same objects), so an
evaluation on them measures generalisation to unseen phrasings, not recall. The mapping
from meaning to words is the same for both, so a checker reads the intent from the
sequence, never from the sentence (``Meaning``).
"""

from __future__ import annotations

import random
from dataclasses import dataclass

import numpy as np

from ..objects.catalogue import CATALOGUE
from .text import GRAB_NOUNS, INTENT_PHRASES, object_noun

# (third person, -ing, imperative or None); {obj} is the noun phrase.
Verb = tuple[str, str, str | None]

TRAIN_VERBS: dict[str, tuple[Verb, ...]] = {
    "lift": (("lifts {obj}", "lifting {obj}", "lift {obj}"),
             ("picks up {obj}", "picking up {obj}", "pick up {obj}"),
             ("picks {obj} up", "picking {obj} up", "pick {obj} up"),
             ("raises {obj}", "raising {obj}", "raise {obj}"),
             ("lifts up {obj}", "lifting up {obj}", "lift up {obj}"),
             ("grabs {obj} and lifts it", "grabbing {obj} and lifting it", "grab {obj} and lift it")),
    "drink": (("drinks from {obj}", "drinking from {obj}", "drink from {obj}"),
              ("sips from {obj}", "sipping from {obj}", "sip from {obj}"),
              ("takes a sip from {obj}", "taking a sip from {obj}", "take a sip from {obj}"),
              ("has a drink from {obj}", "having a drink from {obj}", "have a drink from {obj}")),
    "pour": (("pours from {obj}", "pouring from {obj}", "pour from {obj}"),
             ("pours out {obj}", "pouring out {obj}", "pour out {obj}"),
             ("tips {obj} to pour", "tipping {obj} to pour", "tip {obj} to pour")),
    "inspect": (("inspects {obj}", "inspecting {obj}", "inspect {obj}"),
                ("examines {obj}", "examining {obj}", "examine {obj}"),
                ("looks at {obj}", "looking at {obj}", "look at {obj}"),
                ("checks {obj}", "checking {obj}", "check {obj}")),
    "pass": (("passes {obj}", "passing {obj}", "pass {obj}"),
             ("transfers {obj}", "transferring {obj}", "transfer {obj}"),
             ("switches {obj}", "switching {obj}", "switch {obj}"),
             ("moves {obj}", "moving {obj}", "move {obj}")),
    "offhand": (("hands over {obj}", "handing over {obj}", "hand over {obj}"),
                ("offers {obj}", "offering {obj}", "offer {obj}"),
                ("holds out {obj}", "holding out {obj}", "hold out {obj}"),
                ("gives {obj} away", "giving {obj} away", "give {obj} away")),
}

HELD_OUT_VERBS: dict[str, tuple[Verb, ...]] = {
    "lift": (("hoists {obj}", "hoisting {obj}", "hoist {obj}"),
             ("takes {obj} off the table", "taking {obj} off the table", "take {obj} off the table")),
    "drink": (("drinks out of {obj}", "drinking out of {obj}", "drink out of {obj}"),
              ("brings {obj} to the mouth and drinks", "bringing {obj} to the mouth to drink",
               "bring {obj} to your mouth and drink")),
    "pour": (("empties {obj}", "emptying {obj}", "empty {obj}"),
             ("pours something out of {obj}", "pouring something out of {obj}", "pour something out of {obj}")),
    "inspect": (("studies {obj} closely", "studying {obj} closely", "study {obj} closely"),
                ("takes a close look at {obj}", "taking a close look at {obj}", "take a close look at {obj}")),
    "pass": (("swaps {obj}", "swapping {obj}", "swap {obj}"),
             ("shifts {obj}", "shifting {obj}", "shift {obj}")),
    "offhand": (("presents {obj}", "presenting {obj}", "present {obj}"),
                ("holds {obj} out to someone", "holding {obj} out to someone", "hold {obj} out to someone")),
}

# who -> (subject noun phrases, possessive)
TRAIN_SUBJECTS = {
    "male": (("A man", "The man", "A guy", "He", "Someone", "A person"), "his"),
    "female": (("A woman", "The woman", "A girl", "She", "Someone", "A person"), "her"),
}
HELD_OUT_SUBJECTS = {
    "male": (("A gentleman", "The character", "This man"), "his"),
    "female": (("A lady", "The character", "This woman"), "her"),
}

# Hand wordings; {p} is the possessive ("his", "her", "the"), {s}/{t} a side.
TRAIN_ONE_HAND = ("with {p} {s} hand", "using {p} {s} hand", "in {p} {s} hand", "with the {s} hand", "{s}-handed")
HELD_OUT_ONE_HAND = ("using only {p} {s} hand", "with {p} {s}")
TRAIN_BOTH = ("with both hands", "with two hands", "using both hands", "two-handed")
HELD_OUT_BOTH = ("using both of {p} hands", "holding it in both hands")
TRAIN_PASS = ("from {p} {s} hand to {p} {t}", "from {p} {s} hand to {p} {t} hand", "from the {s} hand to the {t}",
              "from {s} to {t} hand")
HELD_OUT_PASS = ("from the {s} into the {t} hand", "out of {p} {s} hand into {p} {t}")


@dataclass(frozen=True)
class Meaning:
    """What a prompt asks for, independent of its wording."""

    gender: str
    intent: str
    obj_name: str
    hands: str | None = None  # 'left' | 'right' | 'both' | None
    first: str | None = None  # a pass: giver
    last: str | None = None  # a pass: taker

    @staticmethod
    def of(meta: dict) -> Meaning:
        """From a prepared sequence's meta (``dataset.prepare_features``)."""
        return Meaning(meta.get("gender", "neutral"), meta["intent"], meta["object"], meta.get("hands"),
                       meta.get("first"), meta.get("last"))

    @staticmethod
    def of_mode(gender: str, intent: str, obj_name: str, mode: str) -> Meaning:
        """From a SynthGrasp hand mode (``synth.generate.hand_modes``): 'left', 'right',
        'both', or a pass 'giver>taker'."""
        if ">" in mode:
            first, last = mode.split(">")
            return Meaning(gender, intent, obj_name, None, first, last)
        return Meaning(gender, intent, obj_name, mode)

    @property
    def mode(self) -> str:
        """The SynthGrasp hand mode (the inverse of ``of_mode``)."""
        return f"{self.first}>{self.last}" if self.hands is None and self.first else str(self.hands)


def mode_contact(mode: str) -> np.ndarray:
    """(4, 2) [left, right] contact labels from which ``text.hands_from_contact`` reads the
    hand mode back, so that ``text.describe`` names it."""
    c = np.zeros((4, 2), bool)
    if mode == "both":
        c[1:3] = True
    elif ">" in mode:
        giver, taker = (0 if s == "left" else 1 for s in mode.split(">"))
        c[0:2, giver] = True
        c[1:4, taker] = True
    else:
        c[1:3, 0 if mode == "left" else 1] = True
    return c


def object_names(obj_name: str) -> tuple[str, ...]:
    """Every noun naming the object: the catalogue's aliases, or GRAB's plain noun."""
    spec = CATALOGUE.get(obj_name)
    if spec is not None:
        return tuple(spec.aliases)
    return (GRAB_NOUNS.get(obj_name, obj_name),)


def _article(noun: str) -> str:
    return "an" if noun[:1].lower() in "aeiou" else "a"


def _hand_phrase(m: Meaning, poss: str, rng: random.Random, held_out: bool) -> str:
    if m.intent == "pass" and m.first and m.last and m.first != m.last:
        return rng.choice(HELD_OUT_PASS if held_out else TRAIN_PASS).format(p=poss, s=m.first, t=m.last)
    if m.hands == "both":
        return rng.choice(HELD_OUT_BOTH if held_out else TRAIN_BOTH).format(p=poss)
    if m.hands in ("left", "right"):
        return rng.choice(HELD_OUT_ONE_HAND if held_out else TRAIN_ONE_HAND).format(p=poss, s=m.hands)
    return ""


def _verbs(intent: str, held_out: bool) -> tuple[Verb, ...]:
    table = HELD_OUT_VERBS if held_out else TRAIN_VERBS
    if intent in table:
        return table[intent]
    ing, s = INTENT_PHRASES.get(intent, (f"using {{obj}} to {intent}", f"uses {{obj}} to {intent}"))
    return ((s, ing, None),)  # GRAB's other intents: the paper's phrases, no imperative


def one(m: Meaning, rng: random.Random, held_out: bool = False) -> str:
    """One random wording of ``m``."""
    subjects, poss = (HELD_OUT_SUBJECTS if held_out else TRAIN_SUBJECTS).get(
        m.gender, (("A person", "Someone"), "their"))
    verb = rng.choice(_verbs(m.intent, held_out))
    noun = rng.choice(object_names(m.obj_name))
    obj = f"the {noun}" if rng.random() < 0.7 else f"{_article(noun)} {noun}"
    form = rng.random()
    if form < 0.25 and verb[2] is not None:  # imperative: "Pick up the mug with the left hand"
        text = verb[2].format(obj=obj)
        poss = "the" if rng.random() < 0.5 else "your"
    elif form < 0.45:
        text = f"{rng.choice(subjects)} is {verb[1].format(obj=obj)}"
    else:
        text = f"{rng.choice(subjects)} {verb[0].format(obj=obj)}"
    hand = _hand_phrase(m, poss, rng, held_out)
    if hand:
        text = f"{text} {hand}"
    text = text[0].upper() + text[1:]
    case = rng.random()
    if case < 0.15:
        text = text.lower()
    elif case < 0.18:
        text = text.upper()
    return text + ("." if rng.random() < 0.6 else "")


def paraphrases(m: Meaning, n: int, seed: int | str, held_out: bool = False) -> list[str]:
    """``n`` distinct wordings of ``m`` (fewer if the grammar has fewer), the same for the
    same seed."""
    rng = random.Random(f"{seed}|{held_out}")
    out: list[str] = []
    for _ in range(20 * n):
        t = one(m, rng, held_out)
        if t not in out:
            out.append(t)
            if len(out) == n:
                break
    return out


def _all_training_words() -> set[str]:
    """Verb phrases, subjects and hand wordings of the training grammar (for the test that
    the held-out set is disjoint from it)."""
    words = {f for vs in TRAIN_VERBS.values() for v in vs for f in v}
    words |= {s for subs, _ in TRAIN_SUBJECTS.values() for s in subs}
    return words | set(TRAIN_ONE_HAND) | set(TRAIN_BOTH) | set(TRAIN_PASS)


__all__ = ["HELD_OUT_VERBS", "Meaning", "TRAIN_VERBS", "mode_contact", "object_names", "object_noun", "one",
           "paraphrases"]
