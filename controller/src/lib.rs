//! The controller: the paper's control laws as pure functions ([`laws`]), the two loop
//! bodies built from them ([`position_loop`], [`current_loop`]), and the nodes that run
//! those bodies in the stack ([`position_loop_node`], [`current_loop_node`]); and the
//! identification of a motor's parameters ([`identify`], [`identify_node`]).

pub mod current_loop;
pub mod current_loop_node;
pub mod identify;
pub mod identify_node;
pub mod laws;
pub mod position_loop;
pub mod position_loop_node;
