"""The evidential belief map and what is computed on it: ray casting, information gain (and its
brute-force reference)."""
