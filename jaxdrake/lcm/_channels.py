r"""Channel patterns: the subscription language of `LoopbackRelay`, matched in linear time.

A subscription names channels with a regular expression matched against the whole channel
name, as LCM anchors it (`^pattern$`). The relay compiles it to a Thompson NFA and simulates
all its threads at once (a Pike VM without captures), so matching a channel of n characters
takes O(n·m) steps for a pattern of m instructions, whatever the pattern: `(a+)+b` costs no
more than `ab` (a backtracking engine takes 2^n steps on `aaa…a`).

The language is what POSIX extended regexes, PCRE (LCM's own client) and Python's `re`
share: literal characters; `.` (any character but a newline); `[...]` and `[^...]` with
ranges, escapes and `[:alpha:]`-style classes; `\d \w \s \D \W \S`; `\` before any other
punctuation for the literal; the quantifiers `*`, `+`, `?`, `{m}`, `{m,}`, `{m,n}`
(m, n <= 255); `|`; `( )` and `(?: )`; `^` and `$`. A pattern denotes a set of names, so
`*?` is `(x*)?` and possessive or lazy readings do not apply. Refused with a `PatternError`
naming the reason: backreferences, lookaround and the other `(?` groups, any other escape,
a pattern longer than `MAX_LENGTH` characters or compiling to more than `MAX_PROGRAM`
instructions.
"""

from __future__ import annotations

MAX_LENGTH = 255  # characters of a pattern (LCM's own channel names stop at 63)
MAX_PROGRAM = 1000  # instructions emitted while compiling (bounds `{m,n}` expansion too)
MAX_REPEAT = 255

_CHAR, _SPLIT, _JUMP, _START, _END, _MATCH = range(6)

_CLASSES = {
    "d": str.isdecimal, "w": lambda c: c.isalnum() or c == "_", "s": str.isspace,
    "alnum": str.isalnum, "alpha": str.isalpha, "digit": str.isdecimal, "lower": str.islower,
    "upper": str.isupper, "space": str.isspace, "xdigit": lambda c: c in "0123456789abcdefABCDEF",
    "punct": lambda c: c.isascii() and c.isprintable() and not c.isalnum() and c != " ",
}


class PatternError(ValueError):
    """A subscription pattern outside the relay's language."""


class _Chars:
    """A set of characters: ranges and named classes, possibly negated."""

    __slots__ = ("ranges", "tests", "negated")

    def __init__(self, ranges=(), tests=(), negated=False):
        self.ranges, self.tests, self.negated = tuple(ranges), tuple(tests), negated

    def __contains__(self, c):
        hit = any(lo <= c <= hi for lo, hi in self.ranges) or any(test(c) for test in self.tests)
        return hit != self.negated


def _named(letter) -> _Chars:
    """`\\d`, `\\D`, ... as a character set."""
    return _Chars(tests=(_CLASSES[letter.lower()],), negated=letter.isupper())


_ANY = _Chars(ranges=(("\n", "\n"),), negated=True)


class _Parser:
    """Recursive descent to a tree of tuples: ("chars", _Chars), ("cat", [nodes]),
    ("alt", [nodes]), ("repeat", node, lo, hi or None), ("start",), ("end",)."""

    def __init__(self, text):
        self.text, self.pos = text, 0

    def error(self, reason, at=None):
        return PatternError(f"{reason} at position {self.pos if at is None else at}")

    def peek(self):
        return self.text[self.pos] if self.pos < len(self.text) else None

    def take(self):
        c = self.peek()
        self.pos += 1
        return c

    def parse(self):
        node = self.alternation()
        if self.peek() is not None:  # only a ')' stops an alternation early
            raise self.error("unbalanced ')'")
        return node

    def alternation(self):
        branches = [self.sequence()]
        while self.peek() == "|":
            self.take()
            branches.append(self.sequence())
        return branches[0] if len(branches) == 1 else ("alt", branches)

    def sequence(self):
        items = []
        while self.peek() not in (None, "|", ")"):
            items.append(self.quantified())
        return ("cat", items)

    def quantified(self):
        start = self.pos
        node = self.atom()
        while True:
            bounds = self.quantifier()
            if bounds is None:
                return node
            if node[0] in ("start", "end"):
                raise self.error("nothing to repeat", start)
            node = ("repeat", node, *bounds)

    def quantifier(self):
        c = self.peek()
        if c in ("*", "+", "?"):
            self.take()
            return {"*": (0, None), "+": (1, None), "?": (0, 1)}[c]
        if c != "{":
            return None
        end = self.text.find("}", self.pos)
        body = self.text[self.pos + 1:end] if end > 0 else ""
        lo, comma, hi = body.partition(",")
        if not lo.isdecimal() or not (hi.isdecimal() or hi == ""):
            return None  # not a bound: a literal '{', as in Python and PCRE
        lo, hi = int(lo), (int(hi) if hi else None if comma else int(lo))
        if max(lo, hi or 0) > MAX_REPEAT or (hi is not None and hi < lo):
            raise self.error(f"repeat bounds {{{body}}} outside 0 <= m <= n <= {MAX_REPEAT}")
        self.pos = end + 1
        return lo, hi

    def atom(self):
        at, c = self.pos, self.take()
        if c in ("*", "+", "?"):
            raise self.error("nothing to repeat", at)
        if c == "(":
            if self.peek() == "?":
                if self.text[self.pos:self.pos + 2] != "?:":
                    raise self.error("lookaround and other '(?' groups are not supported", at)
                self.pos += 2
            node = self.alternation()
            if self.take() != ")":
                raise self.error("missing ')'", at)
            return node
        if c == "[":
            return ("chars", self.bracket(at))
        if c == ".":
            return ("chars", _ANY)
        if c == "^":
            return ("start",)
        if c == "$":
            return ("end",)
        if c == "\\":
            return ("chars", self.escape(in_brackets=False))
        return ("chars", _Chars(ranges=((c, c),)))

    def escape(self, in_brackets):
        at, c = self.pos - 1, self.take()
        if c is None:
            raise self.error("trailing '\\'", at)
        if c in "dwsDWS":
            return _named(c)
        if c.isdecimal():
            raise self.error("backreferences are not supported", at)
        if c.isalnum() or c == "_":
            raise self.error(f"the escape \\{c} is not supported", at)
        return c if in_brackets else _Chars(ranges=((c, c),))

    def bracket(self, at):
        negated = self.peek() == "^"
        if negated:
            self.take()
        ranges, tests, first = [], [], True
        while True:
            c = self.take()
            if c is None:
                raise self.error("missing ']'", at)
            if c == "]" and not first:
                return _Chars(ranges, tests, negated)
            first = False
            if c == "[" and self.peek() == ":":
                end = self.text.find(":]", self.pos)
                name = self.text[self.pos + 1:end] if end > 0 else ""
                if name not in _CLASSES or len(name) == 1:
                    raise self.error(f"unknown character class [:{name}:]", self.pos - 1)
                tests.append(_CLASSES[name])
                self.pos = end + 2
                continue
            if c == "\\":
                c = self.escape(in_brackets=True)
                if isinstance(c, _Chars):
                    tests.append(c.__contains__)
                    continue
            if self.peek() == "-" and self.text[self.pos + 1:self.pos + 2] not in ("]", ""):
                self.take()
                hi = self.take()
                if hi == "\\":
                    hi = self.escape(in_brackets=True)
                    if isinstance(hi, _Chars):
                        raise self.error("a class cannot end a range", self.pos - 2)
                if hi < c:
                    raise self.error(f"bad range {c}-{hi}", self.pos - 3)
                ranges.append((c, hi))
            else:
                ranges.append((c, c))


def _emit(node, program, budget):
    """Append `node`'s instructions to `program` ([op, x, y] lists; jump targets are indices)."""
    budget[0] -= 1
    if budget[0] < 0 or len(program) > MAX_PROGRAM:
        raise PatternError(f"the pattern expands to more than {MAX_PROGRAM} parts once its repeats are unrolled")
    kind = node[0]
    if kind == "chars":
        program.append([_CHAR, node[1], None])
    elif kind == "start" or kind == "end":
        program.append([_START if kind == "start" else _END, None, None])
    elif kind == "cat":
        for item in node[1]:
            _emit(item, program, budget)
    elif kind == "alt":  # split L1, L2; L1: a; jump end; L2: split ...; last branch; end:
        jumps = []
        for branch in node[1][:-1]:
            split = len(program)
            program.append([_SPLIT, split + 1, None])
            _emit(branch, program, budget)
            jumps.append(len(program))
            program.append([_JUMP, None, None])
            program[split][2] = len(program)
        _emit(node[1][-1], program, budget)
        for jump in jumps:
            program[jump][1] = len(program)
    else:  # repeat: lo copies, then a loop (no upper bound) or hi - lo optional copies
        _, body, lo, hi = node
        for _ in range(lo):
            _emit(body, program, budget)
        for _ in range(1 if hi is None else hi - lo):
            split = len(program)
            program.append([_SPLIT, split + 1, None])
            _emit(body, program, budget)
            if hi is None:
                program.append([_JUMP, split, None])
            program[split][2] = len(program)


class ChannelPattern:
    """A compiled subscription pattern; `fullmatch(channel)` remembers its answers (up to
    `CACHE_SIZE` channels), so each (pattern, channel) pair is matched once."""

    CACHE_SIZE = 4096

    def __init__(self, text: str):
        if len(text) > MAX_LENGTH:
            raise PatternError(f"the pattern is longer than {MAX_LENGTH} characters")
        self.text = text
        self._program = []
        _emit(_Parser(text).parse(), self._program, [MAX_PROGRAM])
        self._program.append([_MATCH, None, None])
        self._cache: dict[str, bool] = {}

    def __repr__(self):
        return f"ChannelPattern({self.text!r})"

    def fullmatch(self, channel: str) -> bool:
        hit = self._cache.get(channel)
        if hit is None:
            hit = self._simulate(channel)
            if len(self._cache) >= self.CACHE_SIZE:
                self._cache.clear()
            self._cache[channel] = hit
        return hit

    def _simulate(self, channel):
        program, n = self._program, len(channel)
        threads = self._closure([0], 0, n)
        for i, c in enumerate(channel):
            threads = self._closure([pc + 1 for pc in threads if program[pc][0] == _CHAR and c in program[pc][1]],
                                    i + 1, n)
            if not threads:
                return False
        return any(program[pc][0] == _MATCH for pc in threads)

    def _closure(self, pcs, pos, n):
        """The instructions reachable from `pcs` without reading a character, at `pos`."""
        program, out, seen, stack = self._program, [], set(), list(pcs)
        while stack:
            pc = stack.pop()
            if pc in seen:
                continue
            seen.add(pc)
            op, x, y = program[pc]
            if op == _JUMP:
                stack.append(x)
            elif op == _SPLIT:
                stack += (y, x)
            elif op == _START:
                if pos == 0:
                    stack.append(pc + 1)
            elif op == _END:
                if pos == n:
                    stack.append(pc + 1)
            else:
                out.append(pc)
        return out
