//! The CRC-64 of OpenIGTLink messages: the ECMA-182 polynomial `0x42F0E1EBA9EA3693`, bits not
//! reflected, initial value 0, no final XOR (catalogued as CRC-64/ECMA-182; OpenIGTLink's
//! `igtl_crc64` and pyigtl's `CRC64` compute it). The `crc` crate's slice-by-16 tables.

use crc::{Crc, Table, CRC_64_ECMA_182};

const ECMA_182: Crc<u64, Table<16>> = Crc::<u64, Table<16>>::new(&CRC_64_ECMA_182);

/// The CRC of `data` continued from `crc`, the CRC of the bytes before it (0 to start): the CRC of
/// `a` then `b` is `crc64_ecma182(b, crc64_ecma182(a, 0))`, as pyigtl's `CRC64(data, crc)` takes it.
pub fn crc64_ecma182(data: &[u8], crc: u64) -> u64 {
    let mut digest = ECMA_182.digest_with_initial(crc);
    digest.update(data);
    digest.finalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bit by bit from the polynomial's definition, as the check of the table-driven one.
    fn bitwise(data: &[u8], mut crc: u64) -> u64 {
        for &byte in data {
            crc ^= u64::from(byte) << 56;
            for _ in 0..8 {
                crc = if crc & (1 << 63) != 0 {
                    (crc << 1) ^ 0x42F0_E1EB_A9EA_3693
                } else {
                    crc << 1
                };
            }
        }
        crc
    }

    #[test]
    fn catalogue_check_value() {
        assert_eq!(crc64_ecma182(b"123456789", 0), 0x6C40_DF5F_0B49_7347);
    }

    #[test]
    fn empty_input_keeps_the_crc() {
        assert_eq!(crc64_ecma182(b"", 0), 0);
        assert_eq!(
            crc64_ecma182(b"", 0x1234_5678_9ABC_DEF0),
            0x1234_5678_9ABC_DEF0
        );
    }

    #[test]
    fn equals_the_bitwise_definition_and_continues_across_splits() {
        // Lengths around the 16-byte stride of the tables, every split point.
        let data: Vec<u8> = (0..67u32)
            .map(|i| (i.wrapping_mul(151) ^ 0x5A) as u8)
            .collect();
        for length in 0..data.len() {
            let whole = crc64_ecma182(&data[..length], 0);
            assert_eq!(whole, bitwise(&data[..length], 0), "length {length}");
            for split in 0..=length {
                let first = crc64_ecma182(&data[..split], 0);
                assert_eq!(crc64_ecma182(&data[split..length], first), whole);
            }
        }
    }
}
