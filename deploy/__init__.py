"""What running MapEx on several machines needs: a Zenoh router and its configuration."""
