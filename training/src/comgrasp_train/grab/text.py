"""Text descriptions of grasp sequences, made as the ComGrasp paper does for GRAB: from
the subject's gender, the intent (the file's ``motion_intent``) and the object, through
several natural-language templates ("A man is taking a picture with a camera").

SynthGrasp additionally names the hand(s) ("... with his left hand", "... from her left
hand to her right"), derived from the contact labels, so a prompt can ask for a hand;
``mention_hands`` switches that on (off for GRAB, as in the paper).
"""

from __future__ import annotations

import numpy as np

from ..objects.catalogue import CATALOGUE

# intent -> (present participle phrase, third-person present phrase); {obj} is the noun phrase.
INTENT_PHRASES: dict[str, tuple[str, str]] = {
    "lift": ("lifting {obj}", "lifts {obj}"),
    "pass": ("passing {obj}", "passes {obj}"),
    "offhand": ("handing over {obj}", "hands over {obj}"),
    "inspect": ("inspecting {obj}", "inspects {obj}"),
    "drink": ("drinking from {obj}", "drinks from {obj}"),
    "pour": ("pouring from {obj}", "pours from {obj}"),
    "use": ("using {obj}", "uses {obj}"),
    "takepicture": ("taking a picture with {obj}", "takes a picture with {obj}"),
    "browse": ("browsing on {obj}", "browses on {obj}"),
    "brush": ("brushing teeth with {obj}", "brushes teeth with {obj}"),
    "call": ("making a call with {obj}", "makes a call with {obj}"),
    "chop": ("chopping with {obj}", "chops with {obj}"),
    "clean": ("cleaning {obj}", "cleans {obj}"),
    "cook": ("cooking with {obj}", "cooks with {obj}"),
    "eat": ("eating {obj}", "eats {obj}"),
    "fly": ("flying {obj}", "flies {obj}"),
    "open": ("opening {obj}", "opens {obj}"),
    "peel": ("peeling {obj}", "peels {obj}"),
    "play": ("playing {obj}", "plays {obj}"),
    "screw": ("screwing in {obj}", "screws in {obj}"),
    "see": ("looking through {obj}", "looks through {obj}"),
    "set": ("setting {obj}", "sets {obj}"),
    "shake": ("shaking {obj}", "shakes {obj}"),
    "squeeze": ("squeezing {obj}", "squeezes {obj}"),
    "stamp": ("stamping with {obj}", "stamps with {obj}"),
    "staple": ("stapling with {obj}", "staples with {obj}"),
    "switchON": ("switching on {obj}", "switches on {obj}"),
    "toast": ("making a toast with {obj}", "makes a toast with {obj}"),
    "wear": ("putting on {obj}", "puts on {obj}"),
}

# GRAB object names that are not plain English nouns.
GRAB_NOUNS = {
    "alarmclock": "alarm clock", "waterbottle": "water bottle", "wineglass": "wine glass",
    "fryingpan": "frying pan", "gamecontroller": "game controller", "stanfordbunny": "bunny",
    "lightbulb": "light bulb", "piggybank": "piggy bank", "doorknob": "door knob",
    "cubesmall": "small cube", "cubemedium": "medium cube", "cubelarge": "large cube",
    "spheresmall": "small sphere", "spheremedium": "medium sphere", "spherelarge": "large sphere",
    "cylindersmall": "small cylinder", "cylindermedium": "medium cylinder", "cylinderlarge": "large cylinder",
    "pyramidsmall": "small pyramid", "pyramidmedium": "medium pyramid", "pyramidlarge": "large pyramid",
    "torussmall": "small torus", "torusmedium": "medium torus", "toruslarge": "large torus",
}

PERSON = {"male": ("man", "his"), "female": ("woman", "her")}
TEMPLATES = (
    "A {person} is {ing}.",
    "The {person} is {ing}.",
    "A {person} {s}.",
    "The {person} {s}.",
)


def object_noun(obj_name: str) -> str:
    if obj_name in GRAB_NOUNS:
        return GRAB_NOUNS[obj_name]
    spec = CATALOGUE.get(obj_name)
    return spec.aliases[0] if spec else obj_name


def _article(noun: str) -> str:
    return "an" if noun[:1].lower() in "aeiou" else "a"


def hands_from_contact(contact: np.ndarray) -> dict:
    """Which hand(s) held the object, from (T, 2) [left, right] contact labels.

    Returns {'hands': 'left'|'right'|'both'|None, 'first': side, 'last': side}: the hand that
    grasped first and the hand still holding at the last contact frame (a pass goes first -> last).
    """
    c = np.asarray(contact, dtype=bool)
    used = [s for s, k in (("left", 0), ("right", 1)) if c[:, k].any()]
    if not used:
        return {"hands": None, "first": None, "last": None}
    first_t = [np.argmax(c[:, k]) if c[:, k].any() else np.inf for k in (0, 1)]
    last_t = [len(c) - 1 - np.argmax(c[::-1, k]) if c[:, k].any() else -1 for k in (0, 1)]
    first = "left" if first_t[0] <= first_t[1] else "right"
    last = "left" if last_t[0] > last_t[1] else "right" if last_t[1] > last_t[0] else first
    return {"hands": used[0] if len(used) == 1 else "both", "first": first, "last": last}


def describe(gender: str, intent: str, obj_name: str, contact: np.ndarray | None = None,
             mention_hands: bool = False) -> list[str]:
    """All template variants for one sequence (training samples one per epoch)."""
    person, poss = PERSON.get(gender, ("person", "their"))
    noun = object_noun(obj_name)
    ing, s = INTENT_PHRASES.get(intent, (f"using {{obj}} to {intent}", f"uses {{obj}} to {intent}"))
    hand_phrase = ""
    if mention_hands and contact is not None:
        h = hands_from_contact(contact)
        if intent == "pass" and h["first"] and h["last"] and h["first"] != h["last"]:
            hand_phrase = f" from {poss} {h['first']} hand to {poss} {h['last']}"
        elif h["hands"] == "both":
            hand_phrase = " with both hands"
        elif h["hands"]:
            hand_phrase = f" with {poss} {h['hands']} hand"
    out = []
    for obj in (f"the {noun}", f"{_article(noun)} {noun}"):
        for t in TEMPLATES:
            out.append(t.format(person=person, ing=ing.format(obj=obj), s=s.format(obj=obj))[:-1] + hand_phrase + ".")
    return out
