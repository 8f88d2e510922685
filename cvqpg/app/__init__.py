"""The application layer, above the library: what a command does around a library call.

Compiling the CPU kernels ahead of a fit with a status line (`compilation`), what a run record says
about the code and the machine (`provenance`), keeping or releasing the heap's freed memory and
measuring peak memory (`allocator`, `provenance`), fitting into a run folder with checkpoints
(`runner`), the commands' workflows: `cvqpg fit` (`inputs`, `fitplan`), `cvqpg compress` and `decompress`
(`compression`), `cvqpg encode` (`encoding`), `eval`, `export`, `info`, `render` and `view` (`runfolders`),
`cvqpg batch` (`batch`, `executors`); where a command may write (`outputs`), what it needs of the machine
(`resources`), how it stops when asked (`signals`) and the thread counts of its environment (`threads`). The
command line and the campaign use it; the library never imports it.
"""
