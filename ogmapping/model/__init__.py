"""What a map renders with: anchor encodings, the hash table's lazy Adam, decoders, the Gaussians' assembly."""
