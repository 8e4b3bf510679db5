"""Instructions in people's words: free text -> the template the model knows, or a refusal that says why.

The model was trained on one template, "go to the {side} side of the {landmark}" (gsmn.task.instructions). People
type "fly behind the red phone booth", "the tank's left side", "land in front of the big tree". `understand(text,
world)` reads such text as a side and a landmark of this world and gives the template to fly, or refuses, saying
why and offering the nearest instructions the world allows. It never guesses between readings:

- **Side.** One of the phrasings in `SIDE_PHRASES` ("left", "to the left of", "left-hand side", "behind", "the far
  side", "in front of", "the near side", ...), anywhere in the text. None, or two different sides ("front left"),
  is refused.
- **Landmark.** The longest run of words that names a catalogue class, directly or through `SYNONYMS` (written from
  the catalogue: "telephone box" -> phone booth, "boulder" -> rock, "xmas tree" -> christmas tree), after spelling
  is mended word by word (`mend`: an edit distance of 1, 2 for words of 7 letters or more, only where one
  vocabulary word is nearest: a word that is itself a vocabulary word is never changed, so no class is turned into
  another) and plurals made singular. A longer name wins over the name inside it, so "red barrel", "wooden house"
  and "lighthouse" stay their own classes and are never read as "barrel" or "house". A head noun that is no class
  itself ("tree", "lamp", "dish") names every class it ends ("fir tree", "palm tree", ...): where exactly one of them
  stands in this world it is that one; where several do, the candidates are offered, one instruction each, and none
  is flown. Two different landmarks named is refused.
- **This world.** A class the world lacks is refused with the world's landmarks; words neither side nor landmark
  ("please", "big", "quickly") are ignored and listed (`Understanding.ignored`), so the page can show them.

Everything here is a pure function of the text and the WorldSpec; tests/test_understand.py reads it over more than
150 phrasings written from the catalogue and the sides.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache

from rapidfuzz.distance import OSA

from gsmn.task.instructions import SIDES, TEMPLATE, Instruction, InstructionError, make_instruction
from gsmn.world.catalogue import NOUN_PHRASES
from gsmn.world.spec import WorldSpec

# Side phrasings, as word sequences (after `words`): the longest found wins over the ones inside it ("far side"
# over "side"). "near" and "far" are a landmark's sides as seen from the start, as the template's front and back.
SIDE_PHRASES: dict[str, tuple[str, ...]] = {
    "left": ("left", "left hand", "lefthand", "to the left of"),
    "right": ("right", "right hand", "righthand", "to the right of"),
    "front": ("front", "in front of", "near side", "nearside", "facing side"),
    "back": ("back", "behind", "rear", "far side", "farside", "back side", "backside", "beyond", "other side"),
}
# Runs of words that hold a side word and name no side: read as filler, the longest run winning as above.
NOT_SIDES = ("back to", "go back", "come back", "fly back", "right next", "right at", "right by", "right there",
             "right now", "right away")

# Other names of the catalogue's classes (gsmn.world.catalogue.NOUN_PHRASES), written class by class. None of them
# is another class's name, and none makes a class of a word inside a longer class ("lamp" is the street lamp, but
# "house" stays the house: it is a class of its own).
SYNONYMS: dict[str, tuple[str, ...]] = {
    "arch": ("archway",),
    "barrel": ("keg", "cask", "drum"),
    "bench": ("park bench",),
    "boat": ("rowboat", "row boat", "dinghy", "canoe", "ship"),
    "box": ("crate", "cardboard box"),
    "bush": ("shrub",),
    "cactus": ("cacti", "saguaro"),
    "car": ("automobile", "sedan", "auto"),
    "christmas tree": ("xmas tree", "x mas tree", "christmastree", "xmastree"),
    "column": ("pillar",),
    "container": ("shipping container",),
    "fir tree": ("fir", "firtree", "pine tree", "pine", "spruce", "conifer"),
    "gorilla": ("ape",),
    "hay bale": ("haybale", "bale of hay", "haystack", "hay"),
    "house": ("home",),
    "igloo": ("snow hut",),
    "lighthouse": ("light house", "beacon"),
    "mailbox": ("mail box", "letterbox", "letter box", "postbox", "post box"),
    "mushroom": ("toadstool",),
    "palm tree": ("palm", "palmtree"),
    "phone booth": ("phonebooth", "telephone booth", "telephone box", "phone box", "phonebox", "call box",
                    "telephone"),
    "pumpkin": ("jack o lantern", "gourd"),
    "rock": ("boulder",),
    "satellite dish": ("satellite", "dish antenna"),
    "snowman": ("snow man",),
    "statue": ("sculpture",),
    "stone circle": ("stonehenge", "ring of stones", "circle of stones"),
    "stop sign": ("stopsign",),
    "street lamp": ("streetlamp", "street light", "streetlight", "lamp post", "lamppost"),
    "tank": ("army tank", "panzer"),
    "tire stack": ("tires", "tyres", "tyre stack", "stack of tires", "stack of tyres", "pile of tires"),
    "totem pole": ("totem",),
    "traffic cone": ("pylon", "safety cone"),
    "water tower": ("water tank", "watertower"),
    "well": ("wishing well",),
    "windmill": ("wind mill",),
    "wooden house": ("cabin", "log cabin", "hut"),
}

# Words that carry no side and no landmark: verbs, politeness, articles, the template's own words.
FILLER = frozenset("""
a an the to of at on by in into onto toward towards side sides please go fly head land move navigate travel get
reach find hover stop go then and now can could you would will just kindly drone quad quadcopter position yourself
me us let s its it is that this there here over up down around i want like need lets some bit little way
""".split())


def words(text: str) -> list[str]:
    """Lower-case words: possessives ("tank's") and hyphens ("right-hand") taken apart, punctuation dropped."""
    text = re.sub(r"['’]s\b", " ", text.lower())
    return re.findall(r"[a-z]+", text)


def _phrases() -> dict[tuple[str, ...], str]:
    """Every name of a class (its noun phrase and its synonyms) as a word tuple -> the class."""
    table = {tuple(p.split()): p for p in NOUN_PHRASES}
    for cls, names in SYNONYMS.items():
        if cls not in NOUN_PHRASES:
            raise ValueError(f"SYNONYMS names {cls!r}, which is not a catalogue class")
        for name in names:
            key = tuple(name.split())
            if table.get(key, cls) != cls:
                raise ValueError(f"the synonym {name!r} of {cls!r} is already {table[key]!r}")
            table[key] = cls
    return table


PHRASES = _phrases()
# A head noun that is no class itself names every class ending with it: "tree" -> christmas, fir and palm tree.
HEADS: dict[str, tuple[str, ...]] = {}
for _phrase in NOUN_PHRASES:
    _head = _phrase.split()[-1]
    if " " in _phrase and (_head,) not in PHRASES:
        HEADS[_head] = (*HEADS.get(_head, ()), _phrase)
SIDE_WORDS: dict[tuple[str, ...], str | None] = {
    **{tuple(p.split()): side for side, phrases in SIDE_PHRASES.items() for p in phrases},
    **{tuple(p.split()): None for p in NOT_SIDES}}
VOCABULARY = frozenset(w for key in (*PHRASES, *SIDE_WORDS) for w in key) | FILLER | frozenset(HEADS)


@lru_cache(maxsize=4096)
def mend(word: str) -> str:
    """A word as the vocabulary spells it: itself if known, its singular if that is known ("boxes", "trees",
    "cacti" is a synonym), else the one vocabulary word nearest by edit distance (transpositions count one) within
    1 (for 4-letter words only two letters swapped: "tnak"), or 2 for words of 8 letters or more; unchanged where
    none is, or where two are equally near. Short words are left alone: "ball" is not a bale, nor "wall" a well."""
    if word in VOCABULARY or len(word) < 4:
        return word
    for cut in ("es", "s"):
        if word.endswith(cut) and word[:-len(cut)] in VOCABULARY:
            return word[:-len(cut)]
    limit = 2 if len(word) >= 8 else 1
    near = [(OSA.distance(word, v), v) for v in VOCABULARY if len(v) >= 4 and abs(len(v) - len(word)) <= limit]
    near = [(d, v) for d, v in near if d <= limit and (len(word) > 4 or sorted(v) == sorted(word))]
    if not near:
        return word
    best = min(d for d, _ in near)
    closest = [v for d, v in near if d == best]
    return closest[0] if len(closest) == 1 else word


def _spans(tokens: list[str], table: dict[tuple[str, ...], str]) -> list[tuple[int, int, str]]:
    """(start, end, value) of every run of `tokens` in `table`, the longest first; a run inside a longer one found
    is dropped ("red barrel" leaves no "barrel")."""
    found = [(i, i + len(key), value) for key, value in table.items()
             for i in range(len(tokens) - len(key) + 1) if tuple(tokens[i:i + len(key)]) == key]
    found.sort(key=lambda s: s[0] - s[1])  # the longest first
    kept: list[tuple[int, int, str]] = []
    for start, end, value in found:
        if not any(a <= start and end <= b for a, b, _ in kept):
            kept.append((start, end, value))
    return sorted(kept)


@dataclass(frozen=True)
class Understanding:
    """What a typed text was understood as, in one world."""

    text: str  # as typed
    instruction: Instruction | None  # the template to fly; None when refused or when several candidates fit
    side: str | None = None
    landmark: str | None = None  # the class understood (a catalogue noun phrase)
    candidates: tuple[Instruction, ...] = ()  # several classes fit ("the tree"): pick one; nothing is flown
    reason: str | None = None  # why it is refused (None when understood)
    suggestions: tuple[str, ...] = ()  # the nearest instructions this world allows, when refused
    ignored: tuple[str, ...] = ()  # words read as neither side nor landmark
    listing: tuple[str, ...] = ()  # the world's landmarks, where the refusal is about a landmark

    @property
    def ok(self) -> bool:
        return self.instruction is not None

    def message(self, tries: int = 4, listing: bool = True) -> str:
        """One line for a person: what is flown, or why not (with the world's landmarks, where `listing` and the
        refusal is about a landmark) and up to `tries` instructions to try instead."""
        if self.instruction is not None:
            return f'understood as "{self.instruction.text}"'
        if self.candidates:
            return (f"{self.reason}; pick one: " + "; ".join(f'"{c.text}"' for c in self.candidates))
        names = f"; this world has: {', '.join(self.listing)}" if listing and self.listing else ""
        offered = "; ".join(f'"{s}"' for s in self.suggestions[:tries])
        return f"{self.reason}{names}" + (f". Try: {offered}" if offered else "")

    def to_dict(self) -> dict:
        return {"text": self.text, "understood": self.instruction.text if self.instruction else None,
                "side": self.side, "landmark": self.landmark, "candidates": [c.text for c in self.candidates],
                "reason": self.reason, "suggestions": list(self.suggestions), "ignored": list(self.ignored),
                "world": list(self.listing)}


def _suggest(world: WorldSpec, side: str | None, asked: str | None) -> tuple[str, ...]:
    """Instructions this world allows, nearest first: the asked landmark's name against the world's (by edit
    distance), then the asked side (else every side of the nearest landmark)."""
    names = sorted({lm.noun_phrase for lm in world.landmarks})
    if asked:
        names.sort(key=lambda n: (OSA.normalized_distance(asked, n), n))
    if side:
        return tuple(TEMPLATE.format(side=side, noun_phrase=n) for n in names)
    if not names:
        return ()
    return tuple(TEMPLATE.format(side=s, noun_phrase=names[0]) for s in SIDES) + tuple(
        TEMPLATE.format(side="left", noun_phrase=n) for n in names[1:])


def understand(text: str, world: WorldSpec) -> Understanding:
    """Read `text` as a side and a landmark of `world` (module docstring): the template to fly, candidates to pick
    from, or a refusal with the reason and the nearest instructions the world allows."""
    raw = words(text)
    tokens = [mend(w) for w in raw]
    side_spans = _spans(tokens, SIDE_WORDS)
    landmark_spans = [s for s in _spans(tokens, PHRASES)
                      if not any(a <= s[0] and s[1] <= b for a, b, _ in side_spans)]
    used = {i for a, b, _ in side_spans + landmark_spans for i in range(a, b)}
    head_spans = [(i, i + 1, tokens[i]) for i in range(len(tokens)) if i not in used and tokens[i] in HEADS]
    used |= {a for a, _, _ in head_spans}
    ignored = tuple(dict.fromkeys(raw[i] for i in range(len(tokens)) if i not in used and tokens[i] not in FILLER))
    sides = list(dict.fromkeys(side for _, _, side in side_spans if side is not None))
    side = sides[0] if len(sides) == 1 else None
    classes = list(dict.fromkeys(cls for _, _, cls in landmark_spans))
    heads = list(dict.fromkeys(head for _, _, head in head_spans))
    in_world = sorted({lm.noun_phrase for lm in world.landmarks})
    asked = classes[0] if len(classes) == 1 else (heads[0] if len(heads) == 1 and not classes else None)

    def refuse(reason: str, landmark: str | None = None, listing: bool = False) -> Understanding:
        return Understanding(text, None, side, landmark, reason=reason,
                             suggestions=_suggest(world, side, landmark or asked), ignored=ignored,
                             listing=tuple(in_world) if listing else ())

    if not raw:
        return refuse("the instruction is empty")
    if len(sides) > 1:
        return refuse(f"several sides named ({', '.join(sides)}); name exactly one")
    if len(classes) + len(heads) > 1 or (heads and classes):
        return refuse(f"several landmarks named ({', '.join(classes + heads)}); name exactly one")
    if not classes and not heads:
        return refuse("no landmark named" + (f" (not a landmark: {', '.join(ignored)})" if ignored else ""),
                      listing=True)
    if classes:
        kinds = classes
    else:  # a head noun: the classes it ends that stand in this world
        kinds = [c for c in HEADS[heads[0]] if c in in_world]
        if not kinds:
            return refuse(f"there is no {heads[0]} in this world", heads[0], listing=True)
    missing = [c for c in kinds if c not in in_world]
    if missing:
        return refuse(f"there is no {missing[0]} in this world", missing[0], listing=True)
    if side is None:  # the suggestions take turns between the landmarks a head noun fits, so the first few name each
        several = f", and several landmarks fit \"{heads[0]}\": {', '.join(kinds)}" if len(kinds) > 1 else ""
        return Understanding(text, None, None, kinds[0] if len(kinds) == 1 else None,
                             reason=f"no side named{several}: say left, right, front (in front of) or back (behind)",
                             suggestions=tuple(TEMPLATE.format(side=s, noun_phrase=k) for s in SIDES for k in kinds),
                             ignored=ignored)
    choices = tuple(make_instruction(world, next(i for i, lm in enumerate(world.landmarks) if lm.noun_phrase == k),
                                     side) for k in kinds)
    if len(choices) > 1:
        return Understanding(text, None, side, None, candidates=choices,
                             reason=f"several landmarks fit \"{heads[0]}\": {', '.join(kinds)}", ignored=ignored)
    return Understanding(text, choices[0], side, kinds[0], ignored=ignored)


def understood_instruction(text: str, world: WorldSpec) -> Instruction:
    """The template `understand` reads in `text`; raises InstructionError with its message otherwise."""
    u = understand(text, world)
    if u.instruction is None:
        raise InstructionError(u.message())
    return u.instruction


def parse_instruction(text: str, world: WorldSpec) -> Instruction:
    """Understand free text such as "fly behind the red phone booth" in `world` as the template the model knows
    (`gsmn.task.understand`): the returned Instruction's text is the template flown. An ambiguous phrase (several
    landmarks of the world share it) resolves to the first of them, with `ambiguous=True`. Raises
    `InstructionError` with a message for users (why, and the nearest instructions this world allows) when no or
    two sides, no or two landmarks, or a landmark this world lacks are named, or several landmark kinds fit.
    """
    return understood_instruction(text, world)
