"""The online map: leaf grid, evidence assignment, leaf fits, kernel cache, the store, queries."""
