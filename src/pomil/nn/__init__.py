"""Neural-network building blocks: recurrent core, encoders, policy heads."""
