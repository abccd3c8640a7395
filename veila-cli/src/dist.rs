//! The old path of the TCP transport, [`crate::transport::tcp`], kept only until `train_cmd.rs`
//! (being split in another branch) names the new one; then this file goes.

pub(crate) use crate::transport::tcp::TcpGroup;
