//! The old path of the NCCL transport, `crate::transport::nccl`, kept only until `train_cmd.rs`
//! (being split in another branch) names the new one; then this file goes.

pub(crate) use crate::transport::nccl::NcclGroup;
