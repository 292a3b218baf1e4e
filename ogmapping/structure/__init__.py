"""The map's structure: Morton codes, the octree and its reach, anchor allocation, the anchors and their colours."""
