"""Export (docs/definitions.md §19): the decision graph, its check and its runtime."""
