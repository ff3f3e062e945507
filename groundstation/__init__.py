"""Ground station that maps structures by touch."""
