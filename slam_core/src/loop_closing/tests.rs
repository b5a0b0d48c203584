//! Tests of the Sim(3) verification.
