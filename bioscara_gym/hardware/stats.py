"""Communication statistics per joint, kept like MH5's communication loops."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class CommStats:
    """Transactions and errors since the last reset and in total.

    A transaction is one attempt on the bus (a retry counts again); an error
    is an attempt that failed (NACK, short or malformed reply).
    """

    transactions: int = 0
    errors: int = 0
    total_transactions: int = 0
    total_errors: int = 0

    def record(self, ok: bool) -> None:
        """Count one attempt, failed unless ``ok``."""
        self.transactions += 1
        self.total_transactions += 1
        if not ok:
            self.errors += 1
            self.total_errors += 1

    def reset(self) -> None:
        """Zero the since-reset counters; totals are kept."""
        self.transactions = 0
        self.errors = 0

    @property
    def error_rate(self) -> float:
        """Errors per transaction since the last reset (0.0 when idle)."""
        return self.errors / self.transactions if self.transactions else 0.0

    def as_dict(self) -> dict[str, float]:
        """The counters as a plain dict (for ``info`` and logs)."""
        return {
            "transactions": self.transactions,
            "errors": self.errors,
            "total_transactions": self.total_transactions,
            "total_errors": self.total_errors,
            "error_rate": self.error_rate,
        }
