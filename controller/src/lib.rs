//! The controller's processes: the nodes that run the loop bodies of `stepdrive-control`
//! in the stack ([`position_loop_node`], [`current_loop_node`]) and the identification
//! sequence in the current loop's place ([`identify_node`]).

pub mod current_loop_node;
pub mod identify_node;
pub mod position_loop_node;
pub mod program;
