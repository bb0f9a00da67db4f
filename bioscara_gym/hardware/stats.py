"""Communication statistics per joint, kept like MH5's communication loops."""

from __future__ import annotations

from dataclasses import dataclass, fields

#: Kinds of failed attempt, as counted by :meth:`CommStats.record`.
ERROR_KINDS = ("bus", "malformed", "implausible")


@dataclass
class CommStats:
    """Transactions, retries and errors (by kind) since the last reset and in total.

    A transaction is one attempt on the bus (a retry counts again); a retry is
    an attempt that repeats a failed one; an error is an attempt that failed,
    of one of three kinds:

    * ``bus``: the bus raised (NACK, absent device, arbitration loss);
    * ``malformed``: the reply has the wrong length, reserved flag bits set, a
      non-finite value, or PING did not answer ``'O'``;
    * ``implausible``: a well-formed reply the joint cannot have sent: a
      position beyond the end stops, a speed beyond the motor, flags the
      command cannot leave (``docs/protocol.md``).

    Every field is an int (the console saves them in its state file).
    """

    transactions: int = 0
    errors: int = 0
    total_transactions: int = 0
    total_errors: int = 0
    retries: int = 0
    bus_errors: int = 0
    malformed: int = 0
    implausible: int = 0
    total_retries: int = 0
    total_bus_errors: int = 0
    total_malformed: int = 0
    total_implausible: int = 0

    def record(self, ok: bool, kind: str = "bus", retry: bool = False) -> None:
        """Count one attempt: failed unless ``ok`` (of ``kind``), a retry if ``retry``.

        Raises:
            ValueError: ``kind`` is not one of :data:`ERROR_KINDS`.
        """
        self.transactions += 1
        self.total_transactions += 1
        if retry:
            self.retries += 1
            self.total_retries += 1
        if not ok:
            if kind not in ERROR_KINDS:
                raise ValueError(f"unknown error kind {kind!r}; expected one of {ERROR_KINDS}")
            counter = "bus_errors" if kind == "bus" else kind
            self.errors += 1
            self.total_errors += 1
            setattr(self, counter, getattr(self, counter) + 1)
            setattr(self, f"total_{counter}", getattr(self, f"total_{counter}") + 1)

    def reset(self) -> None:
        """Zero the since-reset counters; totals are kept."""
        for f in fields(self):
            if not f.name.startswith("total_"):
                setattr(self, f.name, 0)

    @property
    def error_rate(self) -> float:
        """Errors per transaction since the last reset (0.0 when idle)."""
        return self.errors / self.transactions if self.transactions else 0.0

    @property
    def errors_by_kind(self) -> dict[str, int]:
        """Failed attempts since the last reset, by kind (:data:`ERROR_KINDS`)."""
        return {"bus": self.bus_errors, "malformed": self.malformed, "implausible": self.implausible}

    def as_dict(self) -> dict[str, float]:
        """The counters as a plain dict (for ``info`` and logs)."""
        return {
            "transactions": self.transactions,
            "retries": self.retries,
            "errors": self.errors,
            "bus_errors": self.bus_errors,
            "malformed": self.malformed,
            "implausible": self.implausible,
            "total_transactions": self.total_transactions,
            "total_retries": self.total_retries,
            "total_errors": self.total_errors,
            "error_rate": self.error_rate,
        }
