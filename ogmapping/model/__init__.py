"""What a map renders with: anchor encodings, the hash table's row gradients, decoders, the Gaussians' assembly."""
