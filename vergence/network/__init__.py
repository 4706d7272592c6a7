"""The paper's network (issue #34: the first room, where a change to the method lands): `params`, its parameters
and the dynamic window's rule; `retina`, layer 1 (the features I, G, D); `photometric`, the slave's gray levels
onto the master's; `kernel` (and `simd`, its AVX-512 variant), layers 2-4, the correlation of the fovea with every
window of the band; `decide`, winner-takes-all, layer 5 and every check on a decision; `match`, all of it for one
point of one pair. The public names (vergence.match, vergence.Params, ...) come from here. Nothing is imported
here: numba loads only with `retina` or `kernel`."""
