"""The paper's data: the pair protocol, data sets on disk, the embedded scenes."""
