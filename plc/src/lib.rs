pub mod ncmap;
