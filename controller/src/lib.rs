//! The controller: the paper's control laws as pure functions ([`laws`]), the two loop
//! bodies built from them ([`position_loop`], [`current_loop`]), and the processes that run
//! those bodies over iceoryx2 ([`process`]).

pub mod current_loop;
pub mod laws;
pub mod position_loop;
pub mod process;
