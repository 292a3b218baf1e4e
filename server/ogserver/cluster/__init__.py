"""Cluster mode (``ogserver --cluster``): sessions live in named, detached Ray actors; front-ends hold no maps.

Imported only in cluster mode: nothing else in the server needs Ray (the ``cluster`` extra).
"""
