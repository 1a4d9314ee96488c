"""The shape of the code: import circles, the largest modules and the longest functions.

``python bench/code_shape.py [TOP]`` prints the number of import circles among the project's
modules (every import, those inside functions included: tests/test_architecture.py's graph),
then the modules and functions with the most lines of code (not blank, comment or docstring
lines) in gyrocore, sim and experiments, and how many exceed ~800 / ~100 (docs/ARCHITECTURE.md's bounds).
"""

from __future__ import annotations

import ast
import io
import sys
import tokenize
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.test_architecture import _cycles, project_graph  # noqa: E402

MODULE_BOUND = 800
FUNCTION_BOUND = 100


def code_lines(src: str) -> tuple[ast.Module, set[int]]:
    """The parsed module and the line numbers that hold code (not blank, comment or docstring)."""
    tree = ast.parse(src)
    doc: set[int] = set()
    for n in ast.walk(tree):
        if isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and n.body:
            b = n.body[0]
            if (
                isinstance(b, ast.Expr)
                and isinstance(getattr(b, "value", None), ast.Constant)
                and isinstance(b.value.value, str)
            ):
                doc.update(range(b.lineno, b.end_lineno + 1))
    lines: set[int] = set()
    skip = (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER)
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type not in skip:
            lines.update(line for line in range(tok.start[0], tok.end[0] + 1) if line not in doc)
    return tree, lines


def main(top: int = 15) -> None:
    mods, funcs = [], []
    for pkg in ("gyrocore", "sim", "experiments"):
        for p in sorted((REPO / pkg).rglob("*.py")):
            tree, lines = code_lines(p.read_text(encoding="utf-8"))
            rel = p.relative_to(REPO).as_posix()
            mods.append((len(lines), rel))
            for n in ast.walk(tree):
                if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    k = sum(1 for line in lines if n.lineno <= line <= n.end_lineno)
                    funcs.append((k, f"{rel}:{n.lineno} {n.name}"))
    mods.sort(reverse=True)
    funcs.sort(reverse=True)
    print(f"import circles: {len(_cycles(project_graph()))}")
    for what, rows, bound in (("modules", mods, MODULE_BOUND), ("functions", funcs, FUNCTION_BOUND)):
        over = [r for r in rows if r[0] > bound]
        print(
            f"{what} over {bound} lines of code: {len(over)} "
            f"(gyrocore {sum(1 for r in over if r[1].startswith('gyrocore'))})"
        )
        for k, name in rows[:top]:
            print(f"  {k:5d}  {name}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 15)
