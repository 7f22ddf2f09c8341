"""Kernel argument lists read from the kernel source qr-cl owns, not from the driver.

OpenCL promises ``clGetKernelArgInfo`` only for programs built from source with
``-cl-kernel-arg-info``; a program a driver (or pyopencl's on-disk cache) creates from a binary
may have none (Intel's CPU runtime answers KERNEL_ARG_INFO_NOT_AVAILABLE). The launcher binds
arguments by name, so it takes the names and types from the source, preprocessed with the same
``-D`` defines as the build: object-like macros, ``#if``/``#ifdef``/``#ifndef``/``#elif``/
``#else``/``#endif``. Function-like macros are never expanded (a signature that needs one is
refused by name); ``tests/runtime/test_signatures.py`` checks every kernel against the driver's
own answer on PoCL.
"""
from __future__ import annotations

import ast
import re
from dataclasses import dataclass

import numpy as np

#: Element dtype of the OpenCL C scalar types a kernel argument may have (vectors: their base).
CL_TYPES = {"char": np.int8, "uchar": np.uint8, "short": np.int16, "ushort": np.uint16,
            "int": np.int32, "uint": np.uint32, "long": np.int64, "ulong": np.uint64,
            "half": np.float16, "float": np.float32}

_IDENT = re.compile(r"[A-Za-z_]\w*")
_SPACES = {"__global", "global", "__constant", "constant", "__local", "local", "__private", "private"}
_QUALIFIERS = {"const", "restrict", "__restrict", "volatile", "__read_only", "read_only"}


class SignatureError(ValueError):
    """A kernel's argument list could not be read from its source."""


@dataclass(frozen=True)
class KernelArg:
    """One argument of a kernel as its source declares it: ``type_name`` as OpenCL's
    CL_KERNEL_ARG_TYPE_NAME spells it (``"int"``, ``"float3"``, ``"float8*"``), ``space`` the
    address space of a pointer (``"global"``, ``"constant"``, ``"local"``; ``""`` for a value)."""

    name: str
    type_name: str
    space: str

    @property
    def is_buffer(self) -> bool:
        return self.space in ("global", "constant")

    @property
    def dtype(self) -> np.dtype:
        base = re.fullmatch(r"([a-z]+?)(\d*)\*?", self.type_name)
        if base is None or base.group(1) not in CL_TYPES:
            raise TypeError(f"kernel argument {self.name}: unsupported type {self.type_name!r}")
        return np.dtype(CL_TYPES[base.group(1)])

    @property
    def lanes(self) -> int:
        """Vector lanes of a value argument (1 for a scalar)."""
        m = re.search(r"(\d+)$", self.type_name)
        return int(m.group(1)) if m else 1


def _strip_comments(text: str) -> str:
    text = re.sub(r"/\*.*?\*/", lambda m: " " if "\n" not in m.group(0) else "\n" * m.group(0).count("\n"),
                  text, flags=re.S)
    return re.sub(r"//[^\n]*", "", text)


def _expand(text: str, macros: dict[str, str], depth: int = 0) -> str:
    """``text`` with object-like macros replaced until none is left (no self-recursion)."""
    if depth > 64:
        raise SignatureError("macro expansion does not terminate")
    out = _IDENT.sub(lambda m: macros.get(m.group(0), m.group(0)), text)
    return out if out == text else _expand(out, macros, depth + 1)


def _condition(expr: str, macros: dict[str, str], functions: set[str]) -> bool:
    """The value of an ``#if`` expression (integer arithmetic and logic, as C evaluates it)."""
    defined = macros.keys() | functions
    expr = re.sub(r"\bdefined\s*\(\s*(\w+)\s*\)|\bdefined\s+(\w+)",
                  lambda m: "1" if (m.group(1) or m.group(2)) in defined else "0", expr)
    expr = _IDENT.sub(lambda m: "0", _expand(expr, macros))     # undefined names are 0 in C
    expr = re.sub(r"(\d+)[uUlL]+\b", r"\1", expr)
    expr = expr.replace("&&", " and ").replace("||", " or ")
    expr = re.sub(r"!(?!=)", " not ", expr)
    try:
        tree = ast.parse(expr.strip(), mode="eval")
    except SyntaxError as exc:
        raise SignatureError(f"#if {expr!r}: not an integer expression") from exc
    allowed = (ast.Expression, ast.BoolOp, ast.BinOp, ast.UnaryOp, ast.Compare, ast.Constant, ast.And, ast.Or,
               ast.Not, ast.Add, ast.Sub, ast.Mult, ast.FloorDiv, ast.Mod, ast.USub, ast.Eq, ast.NotEq, ast.Lt,
               ast.LtE, ast.Gt, ast.GtE, ast.BitAnd, ast.BitOr, ast.LShift, ast.RShift)
    if not all(isinstance(node, allowed) for node in ast.walk(tree)):
        raise SignatureError(f"#if {expr!r}: unsupported operator")
    return bool(eval(compile(tree, "<#if>", "eval")))


def preprocess(source: str, defines: dict[str, object]) -> tuple[str, dict[str, str]]:
    """(the lines of ``source`` that ``defines`` leave active, the object-like macros defined at
    its end). Line continuations are joined and comments removed first."""
    macros = {k: str(v) for k, v in defines.items()}
    functions: set[str] = set()
    active: list[bool] = []          # per open #if: is its current branch active
    taken: list[bool] = []           # per open #if: has a branch been taken
    kept = []
    for line in _strip_comments(source.replace("\\\n", " ")).splitlines():
        directive = re.match(r"\s*#\s*(\w+)\s*(.*)", line)
        live = all(active)
        if not directive:
            if live:
                kept.append(line)
            continue
        word, rest = directive.group(1), directive.group(2).strip()
        if word in ("if", "ifdef", "ifndef"):
            value = live and (_condition(rest, macros, functions) if word == "if" else
                              ((rest in macros or rest in functions) == (word == "ifdef")))
            active.append(value)
            taken.append(value)
        elif word == "elif":
            value = not taken[-1] and all(active[:-1]) and _condition(rest, macros, functions)
            active[-1], taken[-1] = value, taken[-1] or value
        elif word == "else":
            active[-1], taken[-1] = not taken[-1], True
        elif word == "endif":
            active.pop()
            taken.pop()
        elif word == "define" and live:
            m = re.match(r"(\w+)(\()?", rest)
            if m.group(2):
                functions.add(m.group(1))
            else:
                macros[m.group(1)] = rest[m.end():].strip()
        elif word == "undef" and live:
            macros.pop(rest, None)
            functions.discard(rest)
    if active:
        raise SignatureError("#if without #endif")
    return "\n".join(kept), macros


def _argument(text: str, kernel: str) -> KernelArg:
    tokens = re.findall(r"\*|\w+", text)
    space = next((t.strip("_") for t in tokens if t in _SPACES), "")
    pointer = "*" in tokens
    words = [t for t in tokens if t not in _SPACES and t not in _QUALIFIERS and t != "*"]
    if len(words) < 2:
        raise SignatureError(f"kernel {kernel}: cannot read the argument {text.strip()!r}")
    *type_words, name = words
    type_name = " ".join(type_words)
    type_name = {"unsigned int": "uint", "unsigned char": "uchar", "unsigned long": "ulong",
                 "unsigned short": "ushort", "unsigned": "uint"}.get(type_name, type_name)
    if not re.fullmatch(r"[a-z]+\d*", type_name) or re.sub(r"\d+$", "", type_name) not in CL_TYPES:
        raise SignatureError(f"kernel {kernel}: argument {name} has the type {type_name!r}, which the "
                             "launcher does not know (a typedef or a function-like macro?)")
    if pointer and not space:
        space = "private"
    return KernelArg(name, type_name + ("*" if pointer else ""), space if pointer else "")


def kernel_signatures(source: str, defines: dict[str, object]) -> dict[str, tuple[KernelArg, ...]]:
    """Kernel name -> its arguments, for ``source`` built with ``-D`` ``defines``."""
    text, macros = preprocess(source, defines)
    found = {}
    for m in re.finditer(r"\b(?:__kernel|kernel)\b[^;{(]*?\bvoid\s+(\w+)\s*\(", text):
        depth, i = 1, m.end()
        while depth:
            if i >= len(text):
                raise SignatureError(f"kernel {m.group(1)}: unbalanced parentheses")
            depth += {"(": 1, ")": -1}.get(text[i], 0)
            i += 1
        params = _expand(text[m.end():i - 1], macros).strip()
        parts = [p for p in params.split(",") if p.strip()] if params not in ("", "void") else []
        found[m.group(1)] = tuple(_argument(p, m.group(1)) for p in parts)
    return found
