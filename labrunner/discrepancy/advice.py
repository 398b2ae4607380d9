"""What measurement would separate two causes the data cannot tell apart.

Each pair's sentence belongs to one of the two effects (`Effect.separates`); a pair no
effect speaks for gets a sentence from the two effects' drivers.
"""

from __future__ import annotations

from .terms import Term


def separating_measurement(a: Term, b: Term) -> str:
    for own, other in ((a, b), (b, a)):
        if other.name in own.separates:
            return own.separates[other.name]
    return f"vary {a.driver.split(' (')[0]} independently of {b.driver.split(' (')[0]}"
