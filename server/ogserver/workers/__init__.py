"""Worker mode (``ogserver --workers N``): sessions in child processes of the server, reached over socket pairs."""
