"""How the end of a command left the arm: the safe mode sent, and whether the arm said so.

`ArmClient.make_safe` keeps sending the safe mode and reading the modes back until every
joint confirms it or `SafetyConfig.safe_wait_s` runs out (a link that went down is waited
for meanwhile); `SafeStop.describe()` is the one wording of the outcome every command prints
after "arm left in". It never claims a mode the arm did not report.
"""

from __future__ import annotations

from dataclasses import dataclass

from protocol import Mode


@dataclass(frozen=True)
class SafeStop:
    """The outcome of `ArmClient.make_safe`."""

    mode: Mode
    confirmed: bool
    sent: int  # how many times the safe mode went out
    waited_s: float  # wall time from the first attempt to the verdict
    wait_s: float  # the bound it had
    after_link_back: bool  # the link was down at some point before the verdict
    problem: str = ""  # why it is not confirmed (the last attempt's answer)
    link_down: str | None = None  # the link's state and reason when it ended down

    def describe(self) -> str:
        """What follows "arm left in": the mode only when the arm confirmed it."""
        name = self.mode.name.lower()
        if self.confirmed:
            after = " after the link came back" if self.after_link_back else ""
            return f"{name}{after} (confirmed by the arm)"
        if self.link_down is not None:
            tried = (
                f"{name} sent {_times(self.sent)}, not confirmed ({self.problem}); "
                if self.sent
                else ""
            )
            # "; the driver sends " is what the CLI rewrites (it exits and sends nothing more).
            return (
                f"unknown: {tried}the link is {self.link_down} after waiting {self.wait_s:g} s; "
                f"the driver sends {name} as soon as the arm answers again"
            )
        return (
            f"unknown: {name} sent {_times(self.sent)} in {self.waited_s:.1f} s, not confirmed "
            f"by the arm: {self.problem}"
        )


def _times(n: int) -> str:
    return "once" if n == 1 else f"{n} times"
