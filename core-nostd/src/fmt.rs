//! Logging shim: routes `trace!` .. `error!` to `defmt`, to `log`, or to nothing.
//!
//! With neither feature the macros expand to code that only type-checks its arguments, so a
//! build without logging carries no formatting code at all.
#![allow(unused_macros)]

#[cfg(all(feature = "defmt", feature = "log"))]
compile_error!("the `defmt` and `log` features of cloi-core are mutually exclusive");

macro_rules! log_impl {
    ($level:ident, $($arg:tt)+) => {{
        #[cfg(feature = "defmt")]
        ::defmt::$level!($($arg)+);
        #[cfg(feature = "log")]
        ::log::$level!($($arg)+);
        #[cfg(not(any(feature = "defmt", feature = "log")))]
        {
            let _ = ($($arg)+);
        }
    }};
}

macro_rules! trace { ($($arg:tt)+) => { log_impl!(trace, $($arg)+) }; }
macro_rules! debug { ($($arg:tt)+) => { log_impl!(debug, $($arg)+) }; }
macro_rules! info { ($($arg:tt)+) => { log_impl!(info, $($arg)+) }; }
macro_rules! warn { ($($arg:tt)+) => { log_impl!(warn, $($arg)+) }; }
macro_rules! error { ($($arg:tt)+) => { log_impl!(error, $($arg)+) }; }
