"""Reduced coordinates: closed chains on a spanning tree with loop rows (chains), and one-DoF closed
sub-chains tabulated over their driving angle (tabulated)."""
