"""Real-protocol clients for the chamber, the rate table and the IMU."""
