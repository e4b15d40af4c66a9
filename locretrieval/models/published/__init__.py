"""The descriptors of the paper's benchmark (Sec. 3.8.2), with their authors' weights or recipe:
DenseVLAD (`densevlad`; its dense RootSIFT `dense_sift` with the CPU kernels `densevlad_kernels`, its
vocabulary, VLAD and whitening `vlad`), NetVLAD (`netvlad`), AP-GeM (`apgem`) and DELG's global
branch (`delg`), each reading its authors' weight file and writing it as a locretrieval checkpoint."""
