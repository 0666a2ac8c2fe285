"""What the filter does with the sensors the health monitor judges faulty: one policy object.

``kckf ... --faults isolate|report|off`` and ``Params.faults`` (every path, the smoother, the
likelihood, the fit, the stream and the exported step read it from the parameters, so they
agree by construction):

* ``isolate`` (the default): the monitor (``_health``) runs and a sensor it judges faulty is
  not used until it behaves again; a gyro not used is stood in for where the model allows;
* ``report``: the monitor runs and names what ``isolate`` would take out, but every reading
  the plausibility screen (``_screen``) lets through is used: no estimate changes against
  ``off``;
* ``off``: no monitor: every reading the plausibility screen lets through is used, as before
  the monitor existed (commit eef04aa: the kernel holds a missing gyro's last value).

The plausibility screen (readings outside their range, railed, unreachable through the Hall
curve, at a gyro's full scale) applies under every policy: such a reading is not a
measurement.
"""

from __future__ import annotations

from dataclasses import dataclass

#: The policies, as the command line names them.
FAULT_POLICIES = ("isolate", "report", "off")


@dataclass(frozen=True)
class FaultPolicy:
    """What becomes of a sensor the health monitor judges faulty (module docstring).

    Example:
        >>> FaultPolicy("report").monitors, FaultPolicy("report").isolates
        (True, False)
    """

    mode: str = "isolate"  # one of FAULT_POLICIES

    def __post_init__(self):
        if self.mode not in FAULT_POLICIES:
            raise ValueError(f"FaultPolicy.mode: expected one of {FAULT_POLICIES}, got "
                             f"{self.mode!r}")

    @property
    def monitors(self) -> bool:
        """Whether the health monitor runs (``isolate``, ``report``)."""
        return self.mode != "off"

    @property
    def isolates(self) -> bool:
        """Whether the monitor's decisions take readings out (``isolate``)."""
        return self.mode == "isolate"

    @classmethod
    def of(cls, policy: FaultPolicy | str | None) -> FaultPolicy:
        """``policy`` as a ``FaultPolicy`` (a name of ``FAULT_POLICIES``; ``None``: the
        default, ``isolate``)."""
        if policy is None:
            return cls()
        return policy if isinstance(policy, cls) else cls(policy)

    def __str__(self) -> str:
        return self.mode
