"""Command-line client of the OG-Mapping service (``ogclient``) and the ``make demo`` driver."""
