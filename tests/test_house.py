"""The size of the rooms: hand-written modules, C files and functions stay short enough to find
one's way in. ``python tests/test_house.py`` prints the counts the limits below hold."""
from __future__ import annotations

import ast
import re
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_DIR = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]

#: Limits of the house. A function over FUNCTION_LINES lines is allowed, but only so many.
MODULE_LINES = 1000
C_FILE_LINES = 1200
FUNCTION_LINES = 80
MAX_LONG_PY_FUNCTIONS = 12
MAX_LONG_C_FUNCTIONS = 4


def python_files() -> list[Path]:
    """Every hand-written Python file of the package and its tests (lcm-gen's message classes
    say "automatically generated" in their docstring and are left out)."""
    files = [p for d in PACKAGE_DIR.values() for p in (ROOT / d).rglob("*.py")]
    files += list((ROOT / "tests").glob("*.py"))
    return sorted(p for p in set(files) if "__pycache__" not in p.parts
                  and "automatically generated" not in p.read_text()[:200])


def c_files() -> list[Path]:
    """Hand-written C sources and headers of the runtime (the generated contract, the
    amalgamation and generated models aside: they say GENERATED in their first lines)."""
    out = []
    for p in sorted((ROOT / "runtime_c").rglob("*.[ch]")):
        if "amalgamation" in p.parts or "GENERATED" in "".join(p.read_text().splitlines()[:5]):
            continue
        out.append(p)
    return out


def long_python_functions(limit: int = FUNCTION_LINES) -> list[tuple[int, str]]:
    """(lines, "file:function") of every Python function longer than ``limit`` lines,
    decorators and docstring included, nested functions counted with their parent."""
    out = []
    for path in python_files():
        for node in _outermost_functions(ast.parse(path.read_text())):
            first = min([node.lineno] + [d.lineno for d in node.decorator_list])
            n = node.end_lineno - first + 1
            if n > limit:
                out.append((n, f"{path.relative_to(ROOT)}:{node.name}"))
    return sorted(out, reverse=True)


def _outermost_functions(node: ast.AST) -> Iterator[ast.FunctionDef | ast.AsyncFunctionDef]:
    """The functions and methods below ``node`` that no other function encloses."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield child
        else:
            yield from _outermost_functions(child)


_TOKEN = re.compile(r'"(?:\\.|[^"\\])*"|\'(?:\\.|[^\'\\])*\'|/\*.*?\*/|//[^\n]*|[{}]', re.S)


def c_functions(path: Path) -> list[tuple[int, str]]:
    """(lines, name) of every top-level brace block of a C file that follows a parameter list,
    i.e. every function definition; strings and comments are skipped, so the register lists
    of inline assembly ("push {r4-r11}") do not count as braces."""
    text = path.read_text()
    out, depth, start = [], 0, None
    for m in _TOKEN.finditer(text):
        tok = m.group()
        if tok == "{":
            if depth == 0:
                head = re.sub(r"/\*.*?\*/|//[^\n]*", "", text[max(0, m.start() - 400):m.start()], flags=re.S)
                start = (m.start(), head.rstrip())
            depth += 1
        elif tok == "}":
            depth -= 1
            if depth == 0 and start is not None:
                begin, head = start
                name = _function_name(head)
                if name:
                    first = text.count("\n", 0, begin - len(head) + name[1])
                    last = text.count("\n", 0, m.end())
                    out.append((last - first + 1, name[0]))
                start = None
    return out


def _function_name(head: str) -> tuple[str, int] | None:
    """The name and its offset in ``head`` when ``head`` (the text before a top-level brace)
    ends with a parameter list, i.e. the brace opens a function body."""
    if not head.endswith(")"):
        return None
    depth = 0
    for i in range(len(head) - 1, -1, -1):
        depth += {")": 1, "(": -1}.get(head[i], 0)
        if depth == 0:
            name = re.search(r"(\w+)\s*$", head[:i])
            if name is None or name.group(1) in ("if", "for", "while", "switch", "__attribute__"):
                return None
            return name.group(1), name.start(1)
    return None


def long_c_functions(limit: int = FUNCTION_LINES) -> list[tuple[int, str]]:
    return sorted(((n, f"{p.relative_to(ROOT)}:{name}") for p in c_files()
                   for n, name in c_functions(p) if n > limit), reverse=True)


def long_files(paths: list[Path], limit: int) -> list[tuple[int, str]]:
    return sorted(((n, str(p.relative_to(ROOT))) for p in paths
                   if (n := len(p.read_text().splitlines())) > limit), reverse=True)


def test_no_python_module_over_the_limit():
    assert not long_files(python_files(), MODULE_LINES)


def test_no_c_file_over_the_limit():
    assert not long_files(c_files(), C_FILE_LINES)


def test_few_long_python_functions():
    found = long_python_functions()
    assert len(found) <= MAX_LONG_PY_FUNCTIONS, "\n".join(f"{n} {name}" for n, name in found)


def test_few_long_c_functions():
    found = long_c_functions()
    assert len(found) <= MAX_LONG_C_FUNCTIONS, "\n".join(f"{n} {name}" for n, name in found)


def test_the_c_counter_sees_functions(tmp_path):
    src = tmp_path / "x.c"
    src.write_text('static const int t[2] = {1, 2};\n'
                   'int f(int a)\n{\n    __asm volatile("push {r4-r11}");\n'
                   '    /* } */ if (a) { return 1; }\n    return 0;\n}\n'
                   'struct s { int a; };\n')
    assert c_functions(src) == [(6, "f")]


def main() -> int:
    py, c = python_files(), c_files()
    print(f"Python files: {len(py)}, over {MODULE_LINES} lines: {len(long_files(py, MODULE_LINES))}")
    for n, name in long_files(py, MODULE_LINES):
        print(f"  {n:5d}  {name}")
    print(f"C files: {len(c)}, over {C_FILE_LINES} lines: {len(long_files(c, C_FILE_LINES))}")
    for n, name in long_files(c, C_FILE_LINES):
        print(f"  {n:5d}  {name}")
    for kind, found in (("Python", long_python_functions()), ("C", long_c_functions())):
        print(f"{kind} functions over {FUNCTION_LINES} lines: {len(found)}")
        for n, name in found:
            print(f"  {n:5d}  {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
