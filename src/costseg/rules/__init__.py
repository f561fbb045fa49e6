"""Decision rules and rule groups: what ``--cost``, ``--sweep`` and ``--alpha_sweep`` decide
(docs/definitions.md §1, §2)."""
