"""The paper's experiment campaign, on top of the library: benchmark grids of fits (`bench`), their
tables and figures against the paper's numbers (`report`, `figures`), the recorded results document
(`results`) and rate–distortion points beside the image codecs (`ratedistortion`).

The core package never imports this subpackage; the command line does (`cvqpg bench`, `cvqpg results`).
"""
