"""The parametric body (Anny), its frame conversion, scans and the initial body fit."""
