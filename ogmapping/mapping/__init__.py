"""The map a session builds and what trains it: the map model (its structures, decoders, optimisers and
counters), the tracker that corrects a frame's pose against it, and the mapping steps. ``Mapper`` runs them."""
