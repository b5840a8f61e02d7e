"""diagnostics: rolls every service's diagnostics/<service> up into diagnostics/agg (requirement LOG-2).

A service that stops publishing, or whose liveliness token disappears, is reported STALE —
the aggregator never guesses "OK" for something it has not heard from.
"""
