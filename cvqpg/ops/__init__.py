"""Operations with fast kernels, each a package of the same shape (see `cvqpg.ops.rasterize`)."""
