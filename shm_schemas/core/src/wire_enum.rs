//! One declaration for an enum that crosses a wire as an integer: its variants, their values and
//! their names in one list, from which the table both ways is generated.

/// Declares a `#[repr(u8 | u16 | u32)]` enum whose integer travels in a payload or a serial
/// frame, with `ALL` (the variants in declaration order), `from_repr` (the integer back to its
/// variant, `None` for any other) and `name` (for logs, viewers and replies):
///
/// ```
/// shm_schemas_core::wire_enum! {
///     /// What a lamp shows.
///     pub enum Lamp: u8 {
///         Off = 0 => "off",
///         /// Steady.
///         On = 1 => "on",
///     }
/// }
/// assert_eq!(Lamp::from_repr(1), Some(Lamp::On));
/// assert_eq!(Lamp::from_repr(2), None);
/// assert_eq!(Lamp::On.name(), "on");
/// assert_eq!(Lamp::ALL, [Lamp::Off, Lamp::On]);
/// ```
///
/// Attributes before `enum` (docs, more derives) go onto the enum; it always derives `Debug`,
/// `Clone`, `Copy`, `PartialEq` and `Eq`.
#[macro_export]
macro_rules! wire_enum {
    (@count) => { 0usize };
    (@count $head:ident $($tail:ident)*) => { 1usize + $crate::wire_enum!(@count $($tail)*) };
    (
        $(#[$meta:meta])*
        $vis:vis enum $name:ident: $repr:ident {
            $(
                $(#[$variant_meta:meta])*
                $variant:ident = $value:literal => $label:literal
            ),+ $(,)?
        }
    ) => {
        $(#[$meta])*
        #[repr($repr)]
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        $vis enum $name {
            $(
                $(#[$variant_meta])*
                $variant = $value,
            )+
        }

        impl $name {
            /// Every variant, in declaration order.
            pub const ALL: [Self; $crate::wire_enum!(@count $($variant)+)] = [$(Self::$variant),+];

            /// The variant whose wire value is `value`; `None` for any other value.
            pub const fn from_repr(value: $repr) -> Option<Self> {
                match value {
                    $($value => Some(Self::$variant),)+
                    _ => None,
                }
            }

            /// The variant's name in logs, viewers and replies.
            pub const fn name(self) -> &'static str {
                match self {
                    $(Self::$variant => $label,)+
                }
            }
        }
    };
}
