//! Helpers for the QEMU tests (see `tests/`).
