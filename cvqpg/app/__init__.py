"""The application layer, above the library: what a command does around a library call.

Compiling the CPU kernels ahead of a fit with a status line (`compilation`), what a run record says
about the code and the machine (`provenance`), keeping or releasing the heap's freed memory and
measuring peak memory (`allocator`, `provenance`), fitting into a run folder with checkpoints
(`runner`), and the compression workflows over run folders and files: `cvqpg compress` and `decompress`
(`compression`), `cvqpg encode` (`encoding`). The command line and the campaign use it; the library never
imports it.
"""
